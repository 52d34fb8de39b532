"""Output folders that never cost a user a file.

An output folder (``dem run --out``, ``coupling run --out``, a benchmark's work folder) may
be used only when it is

* new (it does not exist yet), or empty, or
* an earlier output of this tool: it holds the manifest :data:`MANIFEST` and nothing that the
  manifest does not list (besides the tool's own temporary files ``.tmp_thermodem_*``).

An earlier output is refused unless the run continues it (``--restart``) or replaces it
(``--overwrite``: removes exactly the entries the manifest lists, nothing else, then starts
afresh). A folder holding anything else is refused, with or without ``--overwrite``, naming the
first few foreign entries; nothing in it is touched.

The manifest lists every top-level entry the tool wrote (files and folders: ``history.csv``,
``vtk/``, OpenFOAM time folders, ``processor*/``, logs, ...). Entries are recorded BEFORE they
are created, so a run that is killed leaves a folder that can still be overwritten:

* every writer calls :func:`claim` with the path it is about to create; ``dem.output.atomic_write``
  (all DEM files) does it for its callers;
* the gas solver's own entries (time folders, ``processor*``, ``log.*``, ``postProcessing``) are
  adopted by :func:`adopt_solver_entries`, called once per coupling step.

:func:`claim` is a no-op for paths outside a folder claimed by this process, so the writers
also work for files the Python API writes anywhere.
"""
from __future__ import annotations

import fcntl
import json
import os
import secrets
import shutil

from .errors import SceneError

MANIFEST = ".thermodem-manifest.json"
# every temporary file this tool writes starts with this prefix (hidden, and ours alone), so
# that one left by a kill -9 is recognised as ours and removed by the next run in that folder
TMP_PREFIX = ".tmp_thermodem_"
FORMAT = 1
SHOW = 4                      # foreign entries named in a message
# entries the gas solver (OpenFOAM) creates in the case copy it runs in
SOLVER_NAMES = ("postProcessing", "dynamicCode")
SOLVER_PREFIXES = ("processor", "log.")
PNG_SOFTWARE = "thermodem"    # tEXt Software of the PNGs we write (dem render)


class OutputFolderError(SceneError):
    """An output folder or file the tool may not use (bad input: exit status 2 of ``dem`` and
    ``coupling``, which report every SceneError as one line)."""

    def __init__(self, message):
        self.file, self.path, self.message = None, None, message
        ValueError.__init__(self, message)


# --------------------------------------------------------------------------- manifest

class _Folder:
    """A claimed output folder: its manifest, rewritten atomically when an entry is added."""

    def __init__(self, path, entries, command):
        self.path = path
        self.entries = set(entries)
        self.command = command

    def add(self, name):
        if name not in self.entries and name != MANIFEST:
            self.entries.add(name)
            self.save()

    def save(self, merge=True):
        """Write the manifest; ``merge``: keep entries another process (dem render beside a
        running dem run) added since we read it. Processes saving at once take turns (an
        exclusive lock on the folder for the read, merge and replace), each through its own
        temporary file (TMP_PREFIX: a killed writer's is cleaned up like every temporary file of
        ours): with one shared temporary name, two savers at once made one of them fail, and a
        run could stop there (docs/reliability.md)."""
        dfd = os.open(self.path, os.O_RDONLY)
        try:
            try:
                fcntl.flock(dfd, fcntl.LOCK_EX)
            except OSError:   # a file system without locks: the own temporary file still holds
                pass
            if merge:
                try:
                    self.entries |= read_manifest(self.path) or set()
                except OutputFolderError:
                    pass
            data = dict(tool="thermodem", format=FORMAT, command=self.command,
                        note=f"entries written by thermodem; '{TMP_PREFIX}*' are its temporary files. "
                             "--overwrite removes exactly these entries.",
                        entries=sorted(self.entries))
            # (created as open() creates files, honouring the umask: mkstemp's would be 0600)
            tmp = os.path.join(self.path, f"{TMP_PREFIX}{os.getpid()}_{secrets.token_hex(4)}.manifest")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            try:
                with os.fdopen(fd, "w") as fh:
                    json.dump(data, fh, indent=1)
                    fh.write("\n")
                os.replace(tmp, os.path.join(self.path, MANIFEST))
            except BaseException:
                if os.path.lexists(tmp):
                    os.unlink(tmp)
                raise
        finally:
            os.close(dfd)   # (releases the lock)


_claimed: dict[str, _Folder] = {}
_alias: dict[str, str] = {}      # a folder as given -> its real path (adopt_solver_entries, every step)


def _real(path):
    return os.path.realpath(os.fspath(path))


def _valid_name(name):
    return isinstance(name, str) and name not in ("", ".", "..") and os.sep not in name and "/" not in name


def read_manifest(folder):
    """The entries listed in ``folder``'s manifest: a set, or None when it has no manifest.
    Raises OutputFolderError when the manifest is unreadable or not ours."""
    path = os.path.join(folder, MANIFEST)
    if not os.path.lexists(path):
        return None
    try:
        with open(path) as fh:
            data = json.load(fh)
        entries = data["entries"]
        ok = data.get("tool") == "thermodem" and isinstance(entries, list) and all(map(_valid_name, entries))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        ok = False
    if not ok:
        raise OutputFolderError(f"{path}: not a readable thermodem manifest; the folder's contents cannot be "
                                "told apart from a user's files: choose a new --out")
    return set(entries)


def _ours(name, listed):
    return name in listed or name == MANIFEST or name.startswith(TMP_PREFIX) or name == MANIFEST + ".tmp"


def _show(folder, names):
    names = sorted(names)
    shown = [n + ("/" if os.path.isdir(os.path.join(folder, n)) else "") for n in names[:SHOW]]
    more = f" and {len(names) - SHOW} more" if len(names) > SHOW else ""
    return ", ".join(shown) + more


def _inside(child, parent):
    """child (a real path) is parent or below it."""
    return child == parent or child.startswith(parent.rstrip(os.sep) + os.sep)


# --------------------------------------------------------------------------- checks

def check(out, *, overwrite=False, restart=False, protect=(), keep=(), what="--out"):
    """Refuse (OutputFolderError, one line) an output folder the run may not use; read-only.

    protect: folders that ``out`` must not be, lie in or contain (a coupled case folder);
    keep: files/folders that ``--overwrite`` must not remove (the scene, the restart checkpoint).
    Returns "new", "empty" or "output"."""
    if overwrite and restart:
        raise OutputFolderError("--overwrite and --restart exclude each other: --restart continues the run in "
                                f"{what} {out}, --overwrite starts a new one there (removing what the earlier run "
                                "wrote); give one of them")
    if not os.fspath(out):
        raise OutputFolderError(f"{what} is empty; give a folder")
    real = _real(out)
    for p in protect:
        rp = _real(p)
        if _inside(real, rp):
            why = ("is the case folder: the run would replace the case's own files" if real == rp else
                   f"is inside the case folder {p}: a run's output never goes into the case")
            raise OutputFolderError(f"{what} {out} {why}; nothing was touched. Choose a folder outside the case "
                                    f"(e.g. out/{os.path.basename(rp)})")
        if _inside(rp, real):
            raise OutputFolderError(f"the case folder {p} is inside {what} {out}; nothing was touched. Choose an "
                                    "output folder that does not contain the case")
    if os.path.lexists(out) and not os.path.isdir(out):
        raise OutputFolderError(f"{what} {out} is a file, not a folder; choose a folder (it is created when new)")
    if not os.path.exists(out):
        _check_creatable(out, what)
        return "new"
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputFolderError(f"{what} {out} is not writable (permission denied); choose another folder")
    names = os.listdir(out)
    if not names:
        return "empty"
    listed = read_manifest(out)
    if listed is None:
        raise OutputFolderError(f"{what} {out} holds files this tool did not write ({_show(out, names)}): it is "
                                f"neither new, empty nor an earlier thermodem output (no {MANIFEST}); nothing was "
                                f"touched. Choose a new {what}")
    foreign = [n for n in names if not _ours(n, listed)]
    if foreign:
        raise OutputFolderError(f"{what} {out} is an earlier thermodem output but also holds entries it did not "
                                f"write ({_show(out, foreign)}); nothing was touched. Move them out or choose a new "
                                f"{what} (--overwrite removes only the entries listed in {MANIFEST} and refuses while "
                                "anything else is there)")
    if overwrite:
        for k in keep:
            rk = _real(k)
            if _inside(rk, real) and rk != real:
                top = os.path.relpath(rk, real).split(os.sep)[0]
                if top in listed:
                    raise OutputFolderError(f"--overwrite would remove {k} (written by an earlier run in {what} "
                                            f"{out}), which this run reads; copy it elsewhere first or choose a "
                                            f"new {what}")
    elif not restart:
        raise OutputFolderError(f"{what} {out} holds an earlier thermodem output ({len(listed)} entries); add "
                                f"--overwrite to replace it (removes only the entries listed in {MANIFEST}), "
                                f"--restart to continue it, or choose a new {what}")
    return "output"


def _check_creatable(out, what):
    parent = os.path.dirname(os.path.abspath(out))
    while not os.path.exists(parent):
        up = os.path.dirname(parent)
        if up == parent:
            break
        parent = up
    if not os.path.isdir(parent):
        raise OutputFolderError(f"cannot create {what} {out}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputFolderError(f"cannot create {what} {out}: {parent} is not writable (permission denied)")


def claim_folder(out, *, overwrite=False, restart=False, protect=(), keep=(), command="dem run",
                 what="--out", reuse=False):
    """Check ``out`` (see :func:`check`), then make it this process's output folder: with
    ``overwrite`` remove the entries its manifest lists (nothing else), create it, write the
    manifest. ``reuse``: a folder this process claimed already is taken as is (the Python API
    continuing a run). Returns the real path."""
    real = _real(out)
    if reuse and real in _claimed:
        return real
    state = check(out, overwrite=overwrite, restart=restart, protect=protect, keep=keep, what=what)
    try:
        listed = read_manifest(out) if state == "output" else set()
        if state == "output" and overwrite:
            remove_listed(out, listed)
            listed = set()
        os.makedirs(out, exist_ok=True)
        folder = _Folder(real, listed, command)
        # merged unless the listed entries were just removed: another process (dem render
        # beside a running dem run) may have added an entry since ``listed`` was read, and
        # writing ``listed`` alone would drop it (that file then counts as foreign)
        folder.save(merge=not (state == "output" and overwrite))
    except OSError as exc:
        raise OutputFolderError(f"{what} {out}: cannot prepare the output folder: {exc.strerror or exc}") from None
    _claimed[real] = folder
    return real


def remove_listed(out, listed):
    """Remove the manifest's entries (and the tool's temporary files) from ``out``; nothing else.
    Symbolic links are removed, never followed."""
    for name in sorted(listed) + [n for n in os.listdir(out) if n.startswith(TMP_PREFIX)]:
        p = os.path.join(out, name)
        if os.path.isdir(p) and not os.path.islink(p):
            shutil.rmtree(p)
        elif os.path.lexists(p):
            os.unlink(p)


def claim_collective(out, comm=None, root=True, **kw):
    """:func:`claim_folder` on the root rank; its refusal is raised on every rank."""
    err = None
    if root:
        try:
            claim_folder(out, **kw)
        except OutputFolderError as exc:
            err = str(exc)
    if comm is not None:
        err = comm.bcast(err, root=0)
    if err is not None:
        raise OutputFolderError(err)


def manifest_command(folder):
    """The command recorded in ``folder``'s manifest ('' when there is none or it is unreadable)."""
    try:
        with open(os.path.join(folder, MANIFEST)) as fh:
            return json.load(fh).get("command", "")
    except (OSError, ValueError, AttributeError):
        return ""


def _open_existing(folder, listed):
    """Take an earlier output folder as claimed by this process, as it is (a single file is
    added to it, e.g. dem render's PNG)."""
    real = _real(folder)
    if real not in _claimed:
        _claimed[real] = _Folder(real, listed, manifest_command(folder))


def _join(folder, listed, path):
    """Record ``path`` (about to be created in ``folder``) in ``folder``'s manifest when
    ``folder`` is an output folder (``listed``: its entries, None when it is not) we may write."""
    if listed is not None and os.access(folder, os.W_OK):
        _open_existing(folder, listed)
        claim(path)


def join_output(path):
    """Record ``path`` (a file or folder about to be created) in the manifest of the output
    folder that directly holds it, if it is one (an unreadable or foreign manifest: not one);
    nothing otherwise."""
    folder = os.path.dirname(os.path.abspath(path))
    try:
        listed = read_manifest(folder) if os.path.isdir(folder) else None
    except OutputFolderError:
        listed = None
    _join(folder, listed, path)


def release(out):
    """Forget a claimed folder (its manifest stays)."""
    _claimed.pop(_real(out), None)


# --------------------------------------------------------------------------- recording

def claim(path):
    """Record the top-level entry of ``path`` (about to be created) in the manifest of the
    claimed output folder that holds it (the innermost one, when a claimed folder lies in
    another: an animation's folder in a coupled output); no-op when no claimed folder holds it."""
    if not _claimed:
        return
    p = os.path.join(_real(os.path.dirname(os.path.abspath(os.fspath(path)))),
                     os.path.basename(os.path.abspath(os.fspath(path))))
    roots = [root for root in _claimed if p.startswith(root + os.sep)]
    if roots:
        root = max(roots, key=len)
        folder = _claimed[root]
        top = p[len(root) + 1:].split(os.sep)[0]
        if top not in folder.entries:
            folder.add(top)


def is_solver_entry(name):
    """A name the gas solver creates in its case folder: a time folder (a number),
    processor*, log.*, postProcessing, dynamicCode."""
    if name in SOLVER_NAMES or name.startswith(SOLVER_PREFIXES):
        return True
    try:
        float(name)
        return True
    except ValueError:
        return False


def adopt_solver_entries(out):
    """Record the gas solver's entries that appeared in the claimed folder ``out`` (called every
    coupling step: one directory listing). Other new entries stay foreign."""
    key = os.fspath(out)
    real = _alias.get(key)
    if real is None:
        real = _alias[key] = _real(out)
    folder = _claimed.get(real)
    if folder is None:
        return
    try:
        names = os.listdir(folder.path)
    except OSError:
        return
    new = [n for n in names if n not in folder.entries and is_solver_entry(n)]
    if new:
        folder.entries.update(new)
        folder.save()


# --------------------------------------------------------------------------- single files

def png_is_ours(path):
    """The PNG at ``path`` carries our tEXt Software chunk (written by dem render)."""
    try:
        with open(path, "rb") as fh:
            if fh.read(8) != b"\x89PNG\r\n\x1a\n":
                return False
            while True:
                head = fh.read(8)
                if len(head) < 8:
                    return False
                n = int.from_bytes(head[:4], "big")
                kind = head[4:]
                if kind == b"IDAT" or kind == b"IEND" or n > 1 << 20:
                    return False
                data = fh.read(n)
                fh.read(4)
                if kind == b"tEXt":
                    key, _, val = data.partition(b"\0")
                    if key == b"Software" and val.startswith(PNG_SOFTWARE.encode()):
                        return True
    except OSError:
        return False


def claim_file(path, what="--png"):
    """A single output file (a rendered PNG, a figure) may be written when it does not exist,
    or the tool wrote it (listed in its folder's manifest, or a PNG carrying our signature);
    otherwise OutputFolderError. When allowed and its folder is an output folder, the file is
    recorded in that folder's manifest (before it is written)."""
    if os.path.isdir(path):
        raise OutputFolderError(f"{what} {path} is a folder; give a file name ending in .png")
    folder = os.path.dirname(os.path.abspath(path)) or "."
    listed = None
    try:
        listed = read_manifest(folder) if os.path.isdir(folder) else None
    except OutputFolderError:
        pass
    if not os.path.lexists(path):
        _check_creatable(path, what)
    elif not ((listed is not None and os.path.basename(path) in listed) or png_is_ours(path)):
        raise OutputFolderError(f"{what} {path} exists and was not written by this tool; it is left untouched: "
                                "give a new file name with --png")
    _join(folder, listed, path)   # an output folder: the new file joins its manifest
