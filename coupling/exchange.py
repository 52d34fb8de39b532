"""DEM side of the thermodem <-> OpenFOAM (thermoDemFoam) coupling exchange.

Two transports with the same frame layout (see docs/coupling_protocol.md):

* :class:`FileExchange`   -- one file per frame in a directory, written to a hidden
  temporary name and renamed; the reader polls and deletes.
* :class:`SocketExchange` -- TCP on 127.0.0.1 or a Unix socket, each frame prefixed by
  its length (uint64, little-endian).

Frame = 56 byte little-endian header + payload::

    char[8]  magic b"TDEMXCHG"
    uint32   protocol version (2)
    uint32   kind   (1: DEM -> CFD, 2: CFD -> DEM)
    int64    step
    int64    n_cells
    int64    n_fields   (scalar columns)
    float64  time [s]
    uint64   flags      (bit 0 FINAL: the sender stops after this step)
    float64  payload[n_fields][n_cells]   (column-major: one column after another)
    int64    n_scalars
    float64  scalars[n_scalars]  (CFD -> DEM: the gas's energy ledger of the step, see
                                  coupling/energy.py; DEM -> CFD: none)

The DEM sends (kind 1) ``eps, Ksl, Us(3), Simp, Sexp`` (+ with ``[averaging]`` the five
``particle_columns`` of coupling.averaging, + three columns per tied wall, ``wall_columns``: the
particles' heat through its faces of each cell, W; decoded, all the extra columns come back as
``wall_columns``) and receives (kind 2)
``U(3), T, gradp(3), p``. Only numpy and the standard library are used.

Typical DEM loop::

    ex = FileExchange(case_dir / "coupling", timeout=60, peer_process=proc)
    fluid = ex.receive(0)                      # initial gas state
    for n in range(1, n_steps + 1):
        ... advance DEM using fluid["U"], fluid["T"], fluid["gradp"] ...
        ex.send(n, {"eps": eps, "Ksl": ksl, "Us": us, "Simp": simp, "Sexp": sexp},
                final=(n == n_steps))
        fluid = ex.receive(n)
        if ex.peer_final: break
    ex.close()
"""
from __future__ import annotations

import errno
import os
import select
import socket
import struct
import time
from pathlib import Path
from typing import Mapping

import numpy as np

from .errors import CouplingError  # noqa: F401 - raised here, importable from here

__all__ = [
    "CouplingError",
    "FileExchange",
    "SocketExchange",
    "TO_CFD_FIELDS",
    "TO_DEM_FIELDS",
    "encode_frame",
    "decode_frame",
    "PROTOCOL_VERSION",
]

MAGIC = b"TDEMXCHG"
PROTOCOL_VERSION = 3
KIND_TO_CFD = 1
KIND_TO_DEM = 2
FLAG_FINAL = 1
HEADER = struct.Struct("<8sIIqqqdQ")
HEADER_SIZE = HEADER.size  # 56
assert HEADER_SIZE == 56

# (name, number of components), in payload order
TO_CFD_FIELDS: tuple[tuple[str, int], ...] = (
    ("eps", 1),   # gas void fraction [-], 0 < eps <= 1
    ("Ksl", 1),   # drag coefficient [kg/(m^3 s)], force on gas per volume = -Ksl (U - Us)
    ("Us", 3),    # particle (solid) velocity, volume averaged [m/s]
    ("Simp", 1),  # implicit heat source coefficient sum(h A)/V [W/(m^3 K)] >= 0
    ("Sexp", 1),  # explicit heat source sum(h A Tp)/V [W/m^3]
)
TO_DEM_FIELDS: tuple[tuple[str, int], ...] = (
    ("U", 3),      # interstitial gas velocity [m/s]
    ("T", 1),      # gas temperature [K]
    ("gradp", 3),  # pressure gradient [Pa/m]
    ("p", 1),      # pressure [Pa] (includes the hydrostatic part)
)
_LAYOUT = {KIND_TO_CFD: TO_CFD_FIELDS, KIND_TO_DEM: TO_DEM_FIELDS}
_SIDES = {"dem": (KIND_TO_CFD, KIND_TO_DEM), "cfd": (KIND_TO_DEM, KIND_TO_CFD)}


# --------------------------------------------------------------------------- frames

def _n_columns(layout) -> int:
    return sum(c for _, c in layout)


def encode_frame(kind: int, step: int, fields: Mapping[str, np.ndarray], *,
                 time_value: float = 0.0, flags: int = 0, n_cells: int | None = None) -> bytes:
    """Pack ``fields`` into one frame (header + float64 payload + scalars, little-endian);
    the scalars are ``fields["scalars"]`` (none when absent)."""
    layout = _LAYOUT[kind]
    missing = [name for name, _ in layout if name not in fields]
    if missing:
        raise ValueError(f"missing fields {missing}; frame kind {kind} needs "
                         f"{[n for n, _ in layout]}")
    cols = []
    n = n_cells
    extra = None
    if kind == KIND_TO_CFD:   # the particle columns of [averaging], then the tied walls'
        more = [fields[k] for k in ("particle_columns", "wall_columns") if fields.get(k) is not None]
        extra = np.concatenate([np.asarray(a, np.float64) for a in more], axis=1) if more else None
    for name, ncomp in layout:
        a = np.asarray(fields[name], dtype=np.float64)
        want = (a.shape[0] if n is None and a.ndim else n,) + ((ncomp,) if ncomp > 1 else ())
        if a.shape != want:
            raise ValueError(f"field {name!r} must have shape {want}, got {a.shape}")
        n = want[0]
        cols.extend([a] if ncomp == 1 else [a[:, k] for k in range(ncomp)])
    if extra is not None:
        a = np.asarray(extra, dtype=np.float64)
        if a.ndim != 2 or a.shape[0] != n:
            raise ValueError(f"particle_columns / wall_columns must have shape ({n}, k), got {a.shape}")
        cols.extend(a[:, k] for k in range(a.shape[1]))
    payload = np.empty((len(cols), n), dtype="<f8")
    for k, c in enumerate(cols):
        payload[k] = c
    head = HEADER.pack(MAGIC, PROTOCOL_VERSION, kind, int(step), n, len(cols),
                       float(time_value), int(flags))
    sc = np.ascontiguousarray(np.asarray(fields.get("scalars", ()), dtype="<f8").ravel())
    return head + payload.tobytes() + struct.pack("<q", sc.size) + sc.tobytes()


def decode_header(buf: bytes) -> dict:
    if len(buf) < HEADER_SIZE:
        raise ValueError(f"frame of {len(buf)} bytes is shorter than the {HEADER_SIZE} byte header")
    magic, ver, kind, step, n, nf, t, flags = HEADER.unpack_from(buf, 0)
    if magic != MAGIC:
        raise ValueError(f"bad magic {magic!r}")
    if ver != PROTOCOL_VERSION:
        raise ValueError(f"protocol version {ver}, expected {PROTOCOL_VERSION}")
    return dict(kind=kind, step=step, n_cells=n, n_fields=nf, time=t, flags=flags)


def decode_frame(buf: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    """Unpack a frame into (header dict, fields dict). Vector fields are (n, 3)."""
    h = decode_header(buf)
    layout = _LAYOUT.get(h["kind"])
    if layout is None:
        raise ValueError(f"unknown frame kind {h['kind']}")
    n, nf = h["n_cells"], h["n_fields"]
    n_extra = nf - _n_columns(layout)
    if n_extra < 0 or (n_extra and h["kind"] != KIND_TO_CFD):
        raise ValueError(f"frame has {nf} columns, kind {h['kind']} needs {_n_columns(layout)}"
                         + (" (+ one per tied fixed-flux wall)" if h["kind"] == KIND_TO_CFD else ""))
    n_pay = HEADER_SIZE + 8 * n * nf
    ns = struct.unpack_from("<q", buf, n_pay)[0] if len(buf) >= n_pay + 8 else -1
    if ns < 0 or len(buf) != n_pay + 8 + 8 * ns:
        raise ValueError(f"frame size {len(buf)} does not match header ({n} cells x {nf} columns"
                         + (f", {ns} scalars)" if ns >= 0 else ", then the scalar count)"))
    data = np.frombuffer(buf, dtype="<f8", offset=HEADER_SIZE, count=n * nf).reshape(nf, n)
    out: dict[str, np.ndarray] = {}
    k = 0
    for name, ncomp in layout:
        if ncomp == 1:
            out[name] = data[k].astype(np.float64)  # native copy
        else:
            out[name] = np.ascontiguousarray(data[k:k + ncomp].T, dtype=np.float64)
        k += ncomp
    if n_extra:
        out["wall_columns"] = np.ascontiguousarray(data[k:].T, dtype=np.float64)
    out["scalars"] = np.frombuffer(buf, dtype="<f8", offset=n_pay + 8, count=ns).astype(np.float64)
    return h, out


# --------------------------------------------------------------------------- base

class _Exchange:
    def __init__(self, *, timeout: float, side: str, n_cells: int | None, peer_process=None):
        if side not in _SIDES:
            raise ValueError("side must be 'dem' or 'cfd'")
        self.timeout = float(timeout)
        self.side = side
        self.peer = "CFD solver" if side == "dem" else "DEM"
        self.kind_out, self.kind_in = _SIDES[side]
        self.n_cells = n_cells
        self.peer_process = peer_process
        self.peer_final = False      # the peer flagged its last step
        self.last_header: dict | None = None
        self.last_time = 0.0
        self.bytes_sent = 0

    def _err(self, msg: str, step) -> CouplingError:
        return CouplingError(msg, peer=self.peer, step=step)

    def _check_process(self, step):
        pp = self.peer_process
        if pp is not None:
            rc = pp.poll()
            if rc is not None:
                raise self._err(f"{self.peer} process exited with code {rc}", step)

    def _encode(self, step, fields, time_value, final):
        try:
            buf = encode_frame(self.kind_out, step, fields, time_value=time_value,
                               flags=FLAG_FINAL if final else 0, n_cells=self.n_cells)
        except ValueError as e:
            raise self._err(f"cannot encode frame: {e}", step) from None
        self.bytes_sent += len(buf) + 8   # (the socket transport's length prefix; a file's name)
        return buf

    def _decode(self, buf, step):
        try:
            h, fields = decode_frame(buf)
        except ValueError as e:
            raise self._err(f"protocol error: {e}", step) from None
        if h["kind"] != self.kind_in:
            raise self._err(f"frame kind {h['kind']}, expected {self.kind_in}", step)
        if h["step"] != step:
            raise self._err(f"received step {h['step']}, expected {step}", step)
        if self.n_cells is not None and h["n_cells"] != self.n_cells:
            raise self._err(f"frame has {h['n_cells']} cells, expected {self.n_cells}", step)
        self.last_header = h
        self.last_time = h["time"]
        self.peer_final = bool(h["flags"] & FLAG_FINAL)
        return fields

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):  # pragma: no cover - overridden
        pass


# --------------------------------------------------------------------------- file

class FileExchange(_Exchange):
    """File transport: frames ``to_cfd_<step:08d>.bin`` / ``to_dem_<step:08d>.bin``.

    Parameters
    ----------
    directory : the exchange directory (``file { directory ...; }`` of system/couplingDict,
        relative to the case).
    timeout : seconds to wait for a frame before :class:`CouplingError`.
    poll_interval : longest sleep between polls (starts at 0.1 ms, doubles).
    peer_process : optional ``subprocess.Popen`` of the peer, checked while waiting.
    clean : remove stale frames at start (incoming ones only when no live solver has
        written ``cfd.pid``; the solver removes stale frames itself when it starts).
    side : "dem" (default) or "cfd" (to emulate the solver in tests).
    """

    def __init__(self, directory, *, timeout: float = 60.0, poll_interval: float = 2e-3,
                 peer_process=None, clean: bool = True, keep_files: bool = False,
                 n_cells: int | None = None, side: str = "dem"):
        super().__init__(timeout=timeout, side=side, n_cells=n_cells, peer_process=peer_process)
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.poll_interval = float(poll_interval)
        self.keep_files = keep_files
        self._out_prefix = "to_cfd" if side == "dem" else "to_dem"
        self._in_prefix = "to_dem" if side == "dem" else "to_cfd"
        self._peer_pid_file = self.directory / ("cfd.pid" if side == "dem" else "dem.pid")
        self._own_pid_file = self.directory / ("dem.pid" if side == "dem" else "cfd.pid")
        self._peer_pid_seen: int | None = None
        if clean:
            # Our outgoing frames cannot be legitimate yet. Incoming ones are stale only
            # if no live peer has started: a live peer cleans up before it sends step 0.
            peer_live = _pid_alive(_read_pid(self._peer_pid_file))
            for f in self.directory.iterdir():
                n = f.name.lstrip(".")
                if n.startswith(self._out_prefix) or (not peer_live and n.startswith(self._in_prefix)):
                    f.unlink(missing_ok=True)
            if not peer_live:
                self._peer_pid_file.unlink(missing_ok=True)
        tmp = self._own_pid_file.with_name("." + self._own_pid_file.name + ".tmp")
        tmp.write_text(f"{os.getpid()}\n")
        os.replace(tmp, self._own_pid_file)

    def _name(self, prefix: str, step: int) -> Path:
        return self.directory / f"{prefix}_{int(step):08d}.bin"

    def send(self, step: int, fields: Mapping[str, np.ndarray], *, time_value: float = 0.0,
             final: bool = False) -> None:
        buf = self._encode(step, fields, time_value, final)
        target = self._name(self._out_prefix, step)
        tmp = target.with_name("." + target.name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(buf)
        os.replace(tmp, target)

    def _peer_dead(self) -> int | None:
        pid = _read_pid(self._peer_pid_file)
        if pid is not None and _pid_alive(pid):
            self._peer_pid_seen = pid
            return None
        if pid is not None and pid == self._peer_pid_seen:
            return pid
        if pid is None and self._peer_pid_seen is not None and not _pid_alive(self._peer_pid_seen):
            return self._peer_pid_seen
        return None

    def receive(self, step: int) -> dict[str, np.ndarray]:
        name = self._name(self._in_prefix, step)
        t0 = time.monotonic()
        sleep = 1e-4
        last_check = t0 - 1.0  # check at once: learn the peer pid early
        while True:
            try:
                with open(name, "rb") as f:
                    buf = f.read()
            except FileNotFoundError:
                pass
            else:
                if not self.keep_files:
                    name.unlink(missing_ok=True)
                return self._decode(buf, step)
            now = time.monotonic()
            if now - t0 > self.timeout:
                raise self._err(f"timeout ({self.timeout:g} s) waiting for {name}", step)
            if now - last_check > 0.1:
                last_check = now
                self._check_process(step)
                dead = self._peer_dead()
                if dead is not None:
                    raise self._err(f"{self.peer} (pid {dead}) died while waiting for {name}", step)
            time.sleep(sleep)
            sleep = min(2 * sleep, self.poll_interval)

    def close(self) -> None:
        try:
            if _read_pid(self._own_pid_file) == os.getpid():
                self._own_pid_file.unlink(missing_ok=True)
        except OSError:
            pass


def _read_pid(path: Path) -> int | None:
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def _pid_alive(pid: int | None) -> bool:
    if not pid or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # a zombie child still "exists": treat as dead
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return True


# --------------------------------------------------------------------------- socket

class SocketExchange(_Exchange):
    """Socket transport: length-prefixed frames over TCP (127.0.0.1) or a Unix socket.

    By default the DEM side is the server: it binds at construction (``port=0`` picks a
    free port, see :attr:`port`) and accepts the solver's connection lazily on the first
    ``send``/``receive`` (or explicitly with :meth:`accept`). Write the port/path into the
    case's ``system/couplingDict`` (``socket { role client; port N; }``) before starting
    the solver. ``role="client"`` connects instead (solver with ``role server``).
    """

    def __init__(self, *, port: int | None = None, path: str | os.PathLike | None = None,
                 host: str = "127.0.0.1", role: str = "server", timeout: float = 60.0,
                 connect_timeout: float | None = None, peer_process=None,
                 n_cells: int | None = None, side: str = "dem"):
        super().__init__(timeout=timeout, side=side, n_cells=n_cells, peer_process=peer_process)
        if (port is None) == (path is None):
            raise ValueError("give exactly one of port or path")
        if role not in ("server", "client"):
            raise ValueError("role must be 'server' or 'client'")
        self.role = role
        self.host = host
        self.path = str(path) if path is not None else None
        self.connect_timeout = float(connect_timeout if connect_timeout is not None else timeout)
        self._listen: socket.socket | None = None
        self._sock: socket.socket | None = None
        self.port = port
        if role == "server":
            if self.path is not None:
                try:
                    os.unlink(self.path)
                except FileNotFoundError:
                    pass
                s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                s.bind(self.path)
            else:
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind((host, int(port)))
                self.port = s.getsockname()[1]
            s.listen(1)
            self._listen = s

    def grow_buffers(self, n_cells):
        """Let one whole frame fit the kernel's socket buffer: the send then returns at once
        instead of waiting for the solver to drain it (it may be descheduled on busy cores)."""
        if self._sock is None:
            return
        need = 2 * (64 + 8 * 8 * n_cells) + 65536
        for opt in (socket.SO_SNDBUF, socket.SO_RCVBUF):
            try:
                if self._sock.getsockopt(socket.SOL_SOCKET, opt) < need:
                    self._sock.setsockopt(socket.SOL_SOCKET, opt, need)
            except OSError:
                pass

    @property
    def endpoint(self) -> str:
        return f"unix:{self.path}" if self.path else f"{self.host}:{self.port}"

    def accept(self, step: int | None = 0) -> None:
        if self._sock is not None:
            return
        if self.role == "server":
            t0 = time.monotonic()
            while True:
                r, _, _ = select.select([self._listen], [], [], 0.1)
                if r:
                    self._sock, _ = self._listen.accept()
                    break
                self._check_process(step)
                if time.monotonic() - t0 > self.connect_timeout:
                    raise self._err(f"timeout ({self.connect_timeout:g} s) waiting for the "
                                    f"{self.peer} to connect to {self.endpoint}", step)
        else:
            t0 = time.monotonic()
            while True:
                fam = socket.AF_UNIX if self.path else socket.AF_INET
                s = socket.socket(fam, socket.SOCK_STREAM)
                try:
                    s.connect(self.path if self.path else (self.host, int(self.port)))
                    self._sock = s
                    break
                except OSError:
                    s.close()
                    self._check_process(step)
                    if time.monotonic() - t0 > self.connect_timeout:
                        raise self._err(f"timeout ({self.connect_timeout:g} s) connecting to "
                                        f"the {self.peer} at {self.endpoint}", step) from None
                    time.sleep(0.02)
        if not self.path:
            self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.setblocking(False)

    def _send_all(self, data: bytes, step) -> None:
        view = memoryview(data)
        t0 = time.monotonic()
        while view:
            left = self.timeout - (time.monotonic() - t0)
            if left <= 0:
                raise self._err(f"timeout ({self.timeout:g} s) sending to the {self.peer}", step)
            _, w, _ = select.select([], [self._sock], [], min(left, 0.5))
            if not w:
                self._check_process(step)
                continue
            try:
                k = self._sock.send(view)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError as e:
                raise self._err(f"{self.peer} closed the connection ({e.strerror or e}) "
                                "while sending", step) from None
            view = view[k:]

    def _recv_exact(self, n: int, step) -> bytes:
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        t0 = time.monotonic()
        while got < n:
            left = self.timeout - (time.monotonic() - t0)
            if left <= 0:
                raise self._err(f"timeout ({self.timeout:g} s) waiting for the {self.peer}", step)
            r, _, _ = select.select([self._sock], [], [], min(left, 0.5))
            if not r:
                self._check_process(step)
                continue
            try:
                k = self._sock.recv_into(view[got:], n - got)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError as e:
                if e.errno in (errno.ECONNRESET, errno.EPIPE):
                    k = 0
                else:
                    raise self._err(f"receive failed: {e}", step) from None
            if k == 0:
                raise self._err(f"{self.peer} closed the connection (peer died?) while "
                                "receiving", step)
            got += k
        return bytes(buf)

    def send(self, step: int, fields: Mapping[str, np.ndarray], *, time_value: float = 0.0,
             final: bool = False) -> None:
        buf = self._encode(step, fields, time_value, final)
        self.accept(step)
        self._send_all(struct.pack("<Q", len(buf)) + buf, step)

    def receive(self, step: int) -> dict[str, np.ndarray]:
        self.accept(step)
        (length,) = struct.unpack("<Q", self._recv_exact(8, step))
        if length < HEADER_SIZE or length > (1 << 40):
            raise self._err(f"bad frame length {length}", step)
        return self._decode(self._recv_exact(length, step), step)

    def close(self) -> None:
        for s in (self._sock, self._listen):
            if s is not None:
                try:
                    s.close()
                except OSError:
                    pass
        self._sock = self._listen = None
        if self.role == "server" and self.path:
            try:
                os.unlink(self.path)
            except OSError:
                pass
