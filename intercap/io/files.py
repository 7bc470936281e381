"""Small file helpers: every result is written atomically, so a run that dies
halfway never leaves a truncated file that a resumed run would trust, and a
write that fails (a full disk, a read-only folder) leaves no temporary file
behind. Result files take the user's umask, as files opened by hand would."""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np


def user_umask() -> int:
    """The process's umask, read without changing it where Linux shows it (/proc/self/status),
    else by setting it and back."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """The permissions of a new result file: 0o666 less the umask (mkstemp's are 0o600)."""
    return 0o666 & ~user_umask()


def _naming(exc: OSError, path: Path) -> OSError:
    """`exc` naming the file meant (`path`), not its temporary twin nor no file at all."""
    named = None if exc.filename is None else Path(exc.filename)
    twin = named is not None and named.parent == path.parent and named.name.startswith(f".{path.name}.")
    if exc.errno is None or (named is not None and not twin):
        return exc
    return OSError(exc.errno, exc.strerror, str(path))


@contextmanager
def atomic_file(path: str | Path, suffix: str):
    """A temporary file beside `path` (with the user's umask) to write to; when the block ends it
    replaces `path` in one step. On any failure it is removed, and an OSError names `path`."""
    path = Path(path)
    tmp = None
    try:
        tmp = atomic_target(path, suffix)
        yield tmp
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        named = _naming(exc, path)
        if named is exc:
            raise
        raise named from exc
    finally:
        if tmp is not None:
            tmp.unlink(missing_ok=True)


def atomic_target(path: Path, suffix: str) -> Path:
    """A new empty file beside `path` (hidden, named after it) with the user's umask, to be written
    and renamed over `path`; `atomic_file` also removes it when the write fails."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    try:
        os.fchmod(fd, file_mode())
    finally:
        os.close(fd)
    return Path(tmp)


def write_text(path: str | Path, text: str) -> None:
    with atomic_file(path, Path(path).suffix or ".txt") as tmp:
        tmp.write_text(text)


def write_json(path: str | Path, data) -> None:
    text = json.dumps(data, indent=2, default=_to_builtin) + "\n"  # a value JSON cannot hold fails before any file
    with atomic_file(path, ".json") as tmp:
        tmp.write_text(text)


def read_json(path: str | Path):
    return json.loads(Path(path).read_text())


def save_npz(path: str | Path, **arrays) -> None:
    with atomic_file(path, ".npz") as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def save_npy(path: str | Path, array: np.ndarray) -> None:
    with atomic_file(path, ".npy") as tmp, open(tmp, "wb") as f:
        np.save(f, array)


def publish(path: str | Path, public: str | Path) -> None:
    """Show a stage's own result file at `public` (the results folder's top level): a hard link
    where the file system allows, else a copy, replacing what was there atomically. A later
    stage that publishes its own file there leaves this one untouched in the stage folder."""
    path, public = Path(path), Path(public)
    with atomic_file(public, path.suffix) as tmp:
        tmp.unlink()
        try:
            os.link(path, tmp)
        except OSError:
            shutil.copyfile(path, tmp)


def per_frame_result(out_dir: str | Path, stage: str, name: str) -> Path:
    """The per-frame stage's own copy of a result, OUT/<stage>/<name>.

    Results folders written before stages kept their own copies have only the
    top-level file; it is adopted into the stage folder first, so a later
    stage that replaces the top-level file cannot take its own output for
    the per-frame one."""
    out_dir = Path(out_dir)
    own = out_dir / stage / name
    if not own.exists() and (out_dir / name).exists():
        publish(out_dir / name, own)
    return own


def write_point_cloud_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Binary little-endian PLY of (N, 3) float points, optional (N, 3) uint8 colours."""
    path = Path(path)
    points = np.asarray(points, dtype=np.float32)
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    records = np.empty(len(points), dtype=fields)
    records["x"], records["y"], records["z"] = points.T
    if colors is not None:
        colors = np.asarray(colors, dtype=np.uint8)
        records["red"], records["green"], records["blue"] = colors.T
    props = "".join(f"property {'float' if t == 'f4' else 'uchar'} {n}\n" for n, t in fields)
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n{props}end_header\n"
    with atomic_file(path, ".ply") as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(records.tobytes())


def _to_builtin(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")
