"""Small shared helpers: atomic writes, run-folder locks, output checks, progress bars, shape checks.

Imports nothing else from the package except :mod:`plenoctree.errors` (and, lazily, the tree
file reader for :func:`check_output_file`).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import re
import socket
import sys
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

__all__ = [
    "atomic_write",
    "atomic_save_npz",
    "atomic_save_json",
    "run_lock",
    "clean_stale_tmp",
    "check_output_file",
    "check_output_dir",
    "replaceable_output",
    "save_png",
    "progress",
    "LogProgress",
    "to_numpy",
    "vec3",
]


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[Any]:
    """Open ``path.tmp-<pid>`` for writing and move it onto ``path`` only on success.

    A crash or exception inside the block leaves ``path`` untouched (no half-written file).
    Temp files of *dead* processes (left by kill -9) next to ``path`` are removed first
    (:func:`clean_stale_tmp`).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_tmp(path.parent)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


_TMP_RE = re.compile(r"\.tmp-(\d+)(\.[^.]*)?$")
LOCK_NAME = ".plenoctree.lock"           # a run folder's lock file
_held_locks: dict[str, list] = {}        # lock path -> [fd, depth] held by this process


def pid_alive(pid: int) -> bool:
    """True if a process with this id exists on this machine (signal 0 probe)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:        # exists, owned by someone else
        return True
    except OSError:
        return True
    return True


def clean_stale_tmp(folder: str | os.PathLike) -> list[Path]:
    """Remove ``*.tmp-<pid>`` files (and ``.name.tmp-<pid>.ext``) of dead processes in ``folder``.

    What :func:`atomic_write` (and the video writer) leave behind when killed with SIGKILL.
    Files of live processes, and anything not matching the pattern, are left alone. Returns the
    removed paths. Never raises for an unreadable folder.
    """
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for e in entries:
        m = _TMP_RE.search(e.name)
        if m is None or int(m.group(1)) == os.getpid() or pid_alive(int(m.group(1))):
            continue
        try:
            if e.is_file(follow_symlinks=False):
                os.unlink(e.path)
                removed.append(Path(e.path))
        except OSError:
            pass
    return removed


@contextlib.contextmanager
def run_lock(target: str | os.PathLike, command: str = "", folder: bool = True) -> Iterator[Path]:
    """Hold an exclusive lock on a run folder (or output file) for the duration of the block.

    The lock is an ``flock`` on ``<folder>/.plenoctree.lock`` (``folder=False``: on
    ``.<name>.lock`` beside an output file), which names its holder as JSON: pid, host, start time, command. The kernel drops
    the lock when its process dies, so the lock of a killed run is simply taken over. A second
    process gets a :class:`~plenoctree.errors.ConfigError` naming the holder; the same process
    may nest locks on one target (``run`` → ``train``). Folders the lock created are removed
    again if the block fails and leaves them empty. Yields the lock file's path.
    """
    from .errors import ConfigError

    target = Path(target)
    path = target / LOCK_NAME if folder else target.with_name(f".{target.name}.lock")
    key = str(path.resolve()) if path.parent.exists() else str(path.absolute())
    if key in _held_locks:
        _held_locks[key][1] += 1
        try:
            yield path
        finally:
            _held_locks[key][1] -= 1
        return
    created = _missing_folders(path.parent)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:            # no flock (Windows): run without a lock
        with _removed_on_failure(created):
            yield path
        return
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                holder = json.loads(os.read(fd, 4096).decode() or "{}")
            except (OSError, ValueError):
                holder = {}
            os.close(fd)
            who = (f"pid {holder.get('pid', '?')} on {holder.get('host', '?')} since "
                   f"{holder.get('started', '?')}" + (f" ({holder['command']})"
                                                     if holder.get("command") else ""))
            raise ConfigError(f"{target}: in use by another plenoctree process: {who}; wait "
                              "for it to finish or choose another --out") from None
        try:                       # the file may have been unlinked by its last holder
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except OSError:
            same = False
        if same:
            break
        os.close(fd)
    info = {"pid": os.getpid(), "host": socket.gethostname(),
            "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "command": command}
    os.ftruncate(fd, 0)
    os.write(fd, (json.dumps(info) + "\n").encode())
    _held_locks[key] = [fd, 1]
    with _removed_on_failure(created):
        try:
            yield path
        finally:
            del _held_locks[key]
            try:
                os.unlink(path)
            except OSError:
                pass
            os.close(fd)


def _missing_folders(folder: Path) -> list[Path]:
    """The folders from ``folder`` up that do not exist yet, deepest first."""
    missing = []
    f = Path(folder).absolute()
    while not f.exists() and f != f.parent:
        missing.append(f)
        f = f.parent
    return missing


@contextlib.contextmanager
def _removed_on_failure(created: list[Path]) -> Iterator[None]:
    """On an exception in the block, remove the folders of ``created`` (deepest first) that
    are empty: a refused or failed command leaves no empty ``--out`` folder behind."""
    try:
        yield
    except BaseException:
        for d in created:
            try:
                d.rmdir()
            except OSError:
                break
        raise


def _is_plenoctree_file(path: Path) -> bool:
    """A tree (native, svox, ``.plnz``) or another zip of arrays this package writes."""
    from .errors import TreeFormatError
    from ._npz import NpzReader

    try:
        with NpzReader(path) as r:
            keys = set(r.keys())
    except TreeFormatError:
        return False
    return bool(keys & {"format_version", "plnz_version", "quant_map"}) \
        or {"child", "data", "offset"} <= keys


def _is_json_file(path: Path) -> bool:
    """A file of at most 64 MB holding valid JSON (a report this package may have written)."""
    try:
        if path.stat().st_size > 64 << 20:
            return False
        json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError):
        return False
    return True


def _starts_with(*magic: bytes, at: int = 0):
    """A check that a file's bytes at offset ``at`` begin with one of ``magic``."""
    def check(path: Path) -> bool:
        try:
            with open(path, "rb") as f:
                head = f.read(at + max(len(m) for m in magic))
        except OSError:
            return False
        return any(head[at:at + len(m)] == m for m in magic)
    return check


#: What an existing file must look like, by suffix, to be replaced without ``--overwrite``:
#: an output of the same kind (a tree, a JSON report, an image, a video, a mesh). Anything else
#: (``notes.txt`` given to ``--json``) is refused.
_OURS = {
    ".npz": _is_plenoctree_file, ".plnz": _is_plenoctree_file, ".json": _is_json_file,
    ".png": _starts_with(b"\x89PNG"), ".ply": _starts_with(b"ply"),
    ".glb": _starts_with(b"glTF"), ".obj": _starts_with(b"# ", b"v ", b"o ", b"mtllib"),
    ".mp4": _starts_with(b"ftyp", at=4), ".mov": _starts_with(b"ftyp", at=4),
    ".mkv": _starts_with(b"\x1aE\xdf\xa3"), ".webm": _starts_with(b"\x1aE\xdf\xa3"),
}
_KINDS = {"tree": (_is_plenoctree_file, "a tree file"), "json": (_is_json_file, "a JSON file")}


def replaceable_output(path: str | os.PathLike, kind: str | None = None) -> bool:
    """True if the existing file ``path`` looks like an output of ``kind`` (``"tree"``,
    ``"json"``; ``None``: of its suffix's kind, :data:`_OURS`)."""
    p = Path(path)
    check = _KINDS[kind][0] if kind else _OURS.get(p.suffix.lower())
    return bool(check and check(p))


def check_output_file(path: str | os.PathLike, what: str = "--out", overwrite: bool = False,
                      kind: str | None = "tree") -> Path:
    """Check, before any work, that an output file can be written to ``path``.

    Refuses (``ConfigError``, one line naming ``what`` and the path): an existing directory, a
    name too long for the file system, a parent that is a file, does not exist on a read-only
    or virtual file system (``/proc``) or is not writable (probed by creating and removing a
    file there), and an existing file that is not an output of the same kind
    ``kind`` (:func:`replaceable_output`: a stray ``notes.txt`` is never overwritten) unless
    ``overwrite``. Returns ``Path(path)``.
    """
    from .errors import ConfigError

    p = Path(path)
    _check_name_lengths(p, what)
    if p.is_dir():
        raise ConfigError(f"{p}: {what} is a directory; give a file name such as "
                          f"{p / ('tree' + (p.suffix or '.npz'))}")
    _check_creatable(p, p.parent if str(p.parent) else Path("."), what)
    if p.exists() or p.is_symlink():
        if not p.is_file():
            raise ConfigError(f"{p}: {what} exists and is not a regular file")
        if not overwrite and not replaceable_output(p, kind):
            label = _KINDS[kind][1] if kind else f"a {p.suffix or 'suffix-less'} file"
            raise ConfigError(f"{p}: exists and is not {label} written by plenoctree; "
                              f"refusing to overwrite it ({what}: choose another name, delete "
                              "it, or add --overwrite)")
    return p


def check_output_dir(path: str | os.PathLike, what: str = "--out") -> Path:
    """Check, before any work, that ``path`` can be used as an output folder (``ConfigError``).

    Creates nothing: a folder that does not exist yet is probed in its nearest existing
    ancestor, so a command refused later leaves no empty folder behind.
    """
    from .errors import ConfigError

    p = Path(path)
    _check_name_lengths(p, what)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{p}: {what} must be a folder, but a file of that name exists")
    _check_creatable(p, p, what)
    return p


def _check_name_lengths(p: Path, what: str) -> None:
    """``ConfigError`` for a path component or a whole path too long for the file system."""
    from .errors import ConfigError

    for part in p.parts:
        if len(os.fsencode(part)) > 255:
            raise ConfigError(f"{what}: a file or folder name of {len(os.fsencode(part))} "
                              f"bytes is too long (at most 255): {part[:40]}...")
    if len(os.fsencode(str(p.absolute()))) > 4000:
        raise ConfigError(f"{what}: the path is too long ({len(str(p.absolute()))} characters)")


def _check_creatable(p: Path, folder: Path, what: str) -> None:
    """``ConfigError`` unless a file can be created in the nearest existing ancestor of
    ``folder`` (a real, writable folder: probed by creating and removing a temp file)."""
    import tempfile

    from .errors import ConfigError

    anc = folder
    while not (anc.exists() or anc.is_symlink()) and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise ConfigError(f"{p}: {what}: {anc} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".plenoctree-probe-", dir=anc)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ConfigError(f"{p}: {what}: cannot write in folder {anc} "
                          f"({e.strerror or e})") from None


def atomic_save_npz(path: str | os.PathLike, compressed: bool = False, **arrays: np.ndarray) -> None:
    """Save arrays to ``path`` (an ``.npz``) atomically; ``compressed`` uses DEFLATE."""
    with atomic_write(path, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **arrays)


def atomic_save_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    with atomic_write(path, "w") as f:
        json.dump(obj, f, indent=2, sort_keys=False)
        f.write("\n")


def to_numpy(x: Any) -> np.ndarray:
    """``x`` as a numpy array: a torch tensor detached and moved to the CPU (a view of a CPU
    tensor), anything else through ``np.asarray``."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def vec3(x: Any) -> np.ndarray:
    """A scalar or 3 numbers (numpy or torch) as a new float64 ``[3]`` array."""
    return np.broadcast_to(np.asarray(to_numpy(x), np.float64).reshape(-1), (3,)).copy()


def to_uint8(img: Any) -> np.ndarray:
    """Convert a float image in [0, 1] (numpy or torch, [H, W] or [H, W, C]) to uint8."""
    img = to_numpy(img)
    if img.dtype == np.uint8:
        return img
    return (np.clip(np.nan_to_num(img.astype(np.float32)), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def save_png(path: str | os.PathLike, img: Any) -> None:
    """Save an image (float [H, W(, C)] in [0, 1] or uint8) as PNG atomically."""
    from PIL import Image

    arr = to_uint8(img)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    with atomic_write(path, "wb") as f:
        Image.fromarray(arr).save(f, format="PNG")


#: Seconds between two progress lines when stderr is not a terminal (log files, CI, ``run``
#: piped to ``tee``); ``PLENOCTREE_PROGRESS_INTERVAL`` overrides it.
PROGRESS_INTERVAL_S = 10.0


def _fmt_time(seconds: float) -> str:
    s = int(max(seconds, 0) + 0.5)
    h, rem = divmod(s, 3600)
    return f"{h}:{rem // 60:02d}:{rem % 60:02d}" if h else f"{rem // 60}:{rem % 60:02d}"


def _fmt_count(n: float, scale: bool) -> str:
    if not scale:
        return f"{n:.0f}" if float(n).is_integer() else f"{n:.1f}"
    for div, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(n) >= div:
            return f"{n / div:.2f}{suffix}"
    return f"{n:.0f}"


class LogProgress:
    """A progress reporter for non-terminals: one plain line every ``interval`` seconds.

    Same calls as the part of tqdm the package uses (iterate, ``update``, ``set_postfix``,
    ``set_description``, ``close``, ``n``, ``total``, context manager). Each line reads
    ``desc: 45% 450/1000 step [1:23 elapsed, ETA 1:41, 5.42 step/s] loss=0.01``; without a
    total, the count and rate only. A step shorter than ``interval`` prints nothing; a longer one
    also prints a final line when it closes. Lines go to ``sys.stderr`` (looked up per line).
    """

    def __init__(self, iterable: Iterable | None = None, total: float | None = None,
                 desc: str = "", interval: float | None = None, unit: str = "it",
                 unit_scale: bool = False, clock: Any = None, **_: Any) -> None:
        import time

        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.total = total
        self.desc, self.unit, self.unit_scale = desc, unit, bool(unit_scale)
        if interval is None:
            interval = float(os.environ.get("PLENOCTREE_PROGRESS_INTERVAL", PROGRESS_INTERVAL_S))
        self.interval = float(interval)
        self._clock = clock or time.monotonic
        self.start = self._last = self._clock()
        self.n: float = 0
        self.postfix = ""
        self.lines = 0
        self.closed = False

    def __iter__(self) -> Iterator[Any]:
        try:
            for item in self.iterable:  # type: ignore[union-attr]
                yield item
                self.update(1)
        finally:
            self.close()

    def __len__(self) -> int:
        return int(self.total or 0)

    def __enter__(self) -> LogProgress:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def update(self, n: float = 1) -> None:
        self.n += n
        now = self._clock()
        if now - self._last >= self.interval:
            self._last = now
            self._emit(now)

    def set_postfix(self, ordered_dict: Any = None, refresh: bool = True, **kw: Any) -> None:
        items = dict(ordered_dict or {}, **kw)
        self.postfix = " ".join(f"{k}={v}" for k, v in items.items())

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        self.postfix = str(s)

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        self.desc = desc or ""

    def refresh(self) -> None:
        pass

    def write(self, s: str) -> None:
        print(s, file=sys.stderr, flush=True)

    def format_line(self, now: float | None = None) -> str:
        """The progress line as it would be printed at time ``now`` (default: the clock)."""
        elapsed = (self._clock() if now is None else now) - self.start
        rate = self.n / elapsed if elapsed > 0 else 0.0
        count = _fmt_count(self.n, self.unit_scale)
        head = f"{self.desc}: " if self.desc else ""
        if self.total:
            frac = min(max(self.n / self.total, 0.0), 1.0)
            eta = (self.total - self.n) / rate if rate > 0 else float("nan")
            eta_s = _fmt_time(eta) if eta == eta else "?"
            text = (f"{head}{100 * frac:3.0f}% {count}/{_fmt_count(self.total, self.unit_scale)} "
                    f"{self.unit} [{_fmt_time(elapsed)} elapsed, ETA {eta_s}, "
                    f"{_fmt_count(rate, self.unit_scale) if rate >= 10 else f'{rate:.2f}'} "
                    f"{self.unit}/s]")
        else:
            text = (f"{head}{count} {self.unit} [{_fmt_time(elapsed)} elapsed, "
                    f"{rate:.2f} {self.unit}/s]")
        return f"{text} {self.postfix}".rstrip()

    def _emit(self, now: float) -> None:
        self.lines += 1
        print(self.format_line(now), file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if self.lines:                       # only steps long enough to have reported
            self._emit(self._clock())


def progress(iterable: Iterable | None = None, total: float | None = None, desc: str = "",
             disable: bool | None = None, **kw: Any):
    """Progress of a long step on stderr, with % and ETA when ``total`` is known.

    On a terminal: a tqdm bar. Otherwise (log file, CI, a pipe): a :class:`LogProgress`, one
    plain line every ``PROGRESS_INTERVAL_S`` seconds (``PLENOCTREE_PROGRESS_INTERVAL``), nothing
    for steps shorter than that. ``disable=True`` shows nothing; ``None``/``False`` = shown.
    ``total`` may be a float (e.g. seconds of a time budget, updated with ``update(dt)``).
    """
    if disable:
        from tqdm.auto import tqdm

        return tqdm(iterable, total=total, desc=desc, disable=True, **kw)
    if not sys.stderr.isatty():
        return LogProgress(iterable, total=total, desc=desc, **kw)
    from tqdm.auto import tqdm

    return tqdm(iterable, total=total, desc=desc, dynamic_ncols=True, **kw)
