"""The many-to-many transport, DEM side (docs/coupling_protocol.md, "Many-to-many transport").

Every DEM rank is a TCP server for the gas processors that hold cells it owns
(coupling.cells: the owner of a cell is fixed at start-up). Before the solver starts, each
rank writes one plan line per such processor g, ``<folder>/gas<g>/dem<r>`` = ``host port n``;
rank 0 writes ``<folder>/ready`` once every rank has written its lines. Each gas processor
connects to the ranks of its plan, says who it is (``TDEMHELO``, its number, its cell count)
and gets the list of its local cells that rank exchanges, in frame order. Per coupling step
a rank then sends one frame (docs/coupling_protocol.md, version 3; ``n_cells`` = the pair's
cells) to each of its gas processors and receives one from each, all at once (select over
the sockets: no order between pairs, so no pair waits for another). No message holds more
than the cells the two ranks share; nothing is pickled.
"""
from __future__ import annotations

import os
import select
import socket
import struct
import time
from pathlib import Path

import numpy as np

from . import foam_case as fc
from .exchange import FLAG_FINAL, KIND_TO_CFD, KIND_TO_DEM, _Exchange, decode_frame, encode_frame
from .errors import CouplingError

HELLO = struct.Struct("<8sqq")
HELLO_MAGIC = b"TDEMHELO"


def gas_pairs(out: Path, n_gas: int, cells) -> dict:
    """For each gas processor g holding cells this rank owns (``cells``: coupling.cells.
    CellShare): (global cell ids, local ids on g), in the order of g's local cells (set-up:
    reads each processor's cellProcAddressing when the gas is decomposed)."""
    owned = cells.global_ids[cells.owned]
    if n_gas <= 1:
        ids = np.ascontiguousarray(owned, np.int64)
        return {0: (ids, ids.copy())} if ids.size else {}
    pairs = {}
    # the pieces this rank's local mesh came from hold every cell it owns (coupling.pieces);
    # a local mesh cut from the whole mesh: every processor's addressing
    read = cells.pieces_read
    if read:
        from .mesh import read_foam_list
        procs = [(int(p[9:]), read_foam_list(str(Path(out) / p / "constant" / "polyMesh" / "cellProcAddressing")))
                 for p in read]
    else:
        procs = enumerate(fc.cell_proc_addressing(out))
    for g, addr in procs:
        loc = np.flatnonzero(np.isin(addr, owned, assume_unique=True)).astype(np.int64)
        if loc.size:
            pairs[g] = (addr[loc].astype(np.int64), loc)
    return pairs


class M2MExchange(_Exchange):
    """One DEM rank's frames with the gas processors it shares cells with (the peer checks
    and errors of coupling.exchange's transports; the frames are per gas processor)."""

    def __init__(self, rank: int, pairs: dict, folder: Path, *, timeout: float, host: str = "127.0.0.1"):
        super().__init__(timeout=timeout, side="dem", n_cells=None)   # peer_process: rank 0's solver
        self.rank, self.pairs, self.folder = rank, pairs, Path(folder)
        self.rows = {g: glob for g, (glob, _loc) in pairs.items()}   # each pair's cells in the frames' arrays
        self._layout = None
        self.host = host
        self.socks: dict[int, socket.socket] = {}
        self.bytes_received = 0
        self._t0 = None
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, 0))
        s.listen(max(8, len(pairs)))
        self.port = s.getsockname()[1]
        self._listen = s

    def write_plan(self):
        """This rank's plan lines (before the solver starts)."""
        for g, (glob, _loc) in self.pairs.items():
            d = self.folder / f"gas{g}"
            d.mkdir(parents=True, exist_ok=True)
            tmp = d / f".dem{self.rank}.tmp"
            tmp.write_text(f"{self.host} {self.port} {glob.size}\n")
            os.replace(tmp, d / f"dem{self.rank}")

    def on_cells(self, cells):
        """The frames' arrays are of ``cells``'s local mesh (coupling.cells.CellShare): each
        pair's rows there (again after the local mesh was rebuilt)."""
        if self._layout != cells.layout:
            self.rows = {g: cells.local(glob) for g, (glob, _loc) in self.pairs.items()}
            if any(np.any(r < 0) for r in self.rows.values()):
                raise CouplingError(f"DEM rank {self.rank}: its local mesh lacks cells it owns", peer="CFD solver")
            self._layout = cells.layout

    def _err(self, msg, step, g=None):
        return CouplingError(msg, peer=self.peer + (f" processor {g}" if g is not None else ""), step=step)

    # ------------------------------------------------------------------ set-up
    def accept(self, step, wait: float | None = None) -> bool:
        """Accept the gas processors of the plan and tell each its cells (at the first frame).
        Returns True once every one is connected; with ``wait`` (s) it returns False when that
        time passed first (the caller checks with the other ranks, then calls again)."""
        if self._t0 is None:
            self._t0 = time.monotonic()
        t_end = time.monotonic() + (wait if wait is not None else self.timeout + 1.0)
        want = set(self.pairs)
        while want - set(self.socks):
            r, _, _ = select.select([self._listen], [], [], 0.1)
            if not r:
                self._check_process(step)
                if time.monotonic() - self._t0 > self.timeout:
                    left = sorted(want - set(self.socks))
                    raise self._err(f"timeout ({self.timeout:g} s) waiting for gas processor(s) {left} to connect "
                                    f"to DEM rank {self.rank} at {self.host}:{self.port}", step)
                if time.monotonic() > t_end:
                    return False
                continue
            conn, _ = self._listen.accept()
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(self.timeout)
            try:
                magic, g, n_local = HELLO.unpack(_recv_blocking(conn, HELLO.size))
            except (OSError, struct.error) as e:
                conn.close()
                raise self._err(f"bad hello from a gas processor: {e}", step) from None
            if magic != HELLO_MAGIC or g not in self.pairs or g in self.socks:
                conn.close()
                raise self._err(f"unexpected hello {magic!r} from gas processor {g}", step)
            glob, loc = self.pairs[g]
            if loc.size and int(loc.max()) >= n_local:
                conn.close()
                raise self._err(f"gas processor {g} has {n_local} cells, the plan names local cell "
                                f"{int(loc.max())}", step, g)
            body = struct.pack("<qq", self.rank, loc.size) + np.ascontiguousarray(loc, "<i8").tobytes()
            conn.sendall(struct.pack("<Q", len(body)) + body)
            conn.setblocking(False)
            self.socks[g] = conn
        if self._listen is None:
            return True
        self._listen.close()
        self._listen = None
        for conn in self.socks.values():   # one frame fits the kernel buffers: sends return at once
            for opt in (socket.SO_SNDBUF, socket.SO_RCVBUF):
                try:
                    conn.setsockopt(socket.SOL_SOCKET, opt, 1 << 22)
                except OSError:
                    pass
        return True

    # ------------------------------------------------------------------ per step
    def send(self, step, fields, *, time_value=0.0, final=False):
        """The frame of every pair: ``fields`` indexed by cell of the local mesh (on_cells: this
        rank's owned entries are sent), wall_columns included."""
        out = {}
        for g, (glob, _loc) in self.pairs.items():
            rows = self.rows[g]
            sub = {k: np.asarray(v)[rows] for k, v in fields.items() if k != "scalars"}
            buf = encode_frame(KIND_TO_CFD, step, sub, time_value=time_value,
                               flags=FLAG_FINAL if final else 0, n_cells=glob.size)
            out[g] = memoryview(struct.pack("<Q", len(buf)) + buf)
        t0 = time.monotonic()
        while out:
            _, w, _ = select.select([], [self.socks[g] for g in out], [], 0.5)
            if not w:
                self._check_process(step)
                if time.monotonic() - t0 > self.timeout:
                    raise self._err(f"timeout ({self.timeout:g} s) sending to gas processors {sorted(out)}", step)
                continue
            for g in [g for g in out if self.socks[g] in w]:
                try:
                    k = self.socks[g].send(out[g])
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError as e:
                    raise self._err(f"closed the connection ({e.strerror or e}) while sending", step, g) from None
                self.bytes_sent += k
                out[g] = out[g][k:]
                if not out[g]:
                    del out[g]

    def receive(self, step, fields_into: dict):
        """One frame from every pair, scattered into ``fields_into`` (arrays indexed by cell
        of the local mesh: on_cells); returns the frames' scalars (the gas's, the same in every
        frame)."""
        pend = {g: [bytearray(8), 0, None] for g in self.pairs}   # buffer, filled, frame length
        done = {}
        t0 = time.monotonic()
        while pend:
            r, _, _ = select.select([self.socks[g] for g in pend], [], [], 0.5)
            if not r:
                self._check_process(step)
                if time.monotonic() - t0 > self.timeout:
                    raise self._err(f"timeout ({self.timeout:g} s) waiting for gas processors {sorted(pend)}", step)
                continue
            for g in [g for g in pend if self.socks[g] in r]:
                buf, got, length = pend[g]
                try:
                    k = self.socks[g].recv_into(memoryview(buf)[got:], len(buf) - got)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:
                    k = 0
                if k == 0:
                    raise self._err("closed the connection (solver died?) while the DEM received", step, g)
                self.bytes_received += k
                got += k
                if got == len(buf):
                    if length is None:
                        (length,) = struct.unpack("<Q", bytes(buf))
                        if length < 56 or length > (1 << 40):
                            raise self._err(f"bad frame length {length}", step, g)
                        pend[g] = [bytearray(length), 0, length]
                        continue
                    done[g] = bytes(buf)
                    del pend[g]
                    continue
                pend[g][1] = got
        scalars, flags = None, set()
        for g in sorted(done):
            glob = self.pairs[g][0]
            try:
                h, f = decode_frame(done[g])
            except ValueError as e:
                raise self._err(f"protocol error: {e}", step, g) from None
            if h["kind"] != KIND_TO_DEM or h["step"] != step or h["n_cells"] != glob.size:
                raise self._err(f"frame kind {h['kind']} step {h['step']} with {h['n_cells']} cells, expected "
                                f"kind {KIND_TO_DEM} step {step} with {glob.size}", step, g)
            for k, a in f.items():
                if k == "scalars":
                    continue
                dst = fields_into.get(k)
                if dst is None:
                    dst = fields_into[k] = np.zeros((fields_into["_n"],) + a.shape[1:])
                dst[self.rows[g]] = a
            if scalars is None:
                scalars = f["scalars"]
            flags.add(int(h["flags"]))
            self.last_header = h
        if len(flags) > 1:
            raise self._err(f"gas processors sent different flags {sorted(flags)}", step)
        self.peer_final = bool(self.last_header["flags"] & FLAG_FINAL) if self.last_header else False
        return scalars if scalars is not None else np.zeros(0)

    def close(self):
        for s in list(self.socks.values()) + ([self._listen] if self._listen is not None else []):
            try:
                s.close()
            except OSError:
                pass
        self.socks = {}
        self._listen = None


def _recv_blocking(conn, n):
    buf = bytearray()
    while len(buf) < n:
        b = conn.recv(n - len(buf))
        if not b:
            raise OSError("connection closed")
        buf += b
    return bytes(buf)
