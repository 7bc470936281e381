"""Atomic result files: a failed write leaves the old file and no temporary file; new files take the umask."""
from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from intercap.io import files
from intercap.io.files import publish, save_npy, save_npz, write_json, write_text


def no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.mark.parametrize("write", [
    lambda p: save_npy(p / "body_vertices.npy", np.ones((2, 3), np.float32)),
    lambda p: save_npz(p / "object_poses.npz", t=np.zeros((2, 3))),
])
def test_a_full_disk_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch, write):
    """np.save failing halfway (ENOSPC): the error names the result file, the earlier file is
    untouched, and no `.body_vertices.npy.XXXX.npy` stays behind."""
    write(tmp_path)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    monkeypatch.setattr(np, "save", no_space)
    monkeypatch.setattr(np, "savez", no_space)
    with pytest.raises(OSError) as caught:
        write(tmp_path)
    assert caught.value.errno == errno.ENOSPC
    assert Path(caught.value.filename).parent == tmp_path and caught.value.filename.endswith(tuple(before))
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # nothing new, nothing changed


def test_a_failed_rename_or_link_leaves_no_temporary(tmp_path, monkeypatch):
    """os.replace failing (a read-only remount, say) after the temporary is written, for json and
    for `publish`'s hard link: the error names the target and the folder holds only what it held."""
    own = tmp_path / "body" / "contact.npy"
    save_npy(own, np.zeros(3, bool))
    monkeypatch.setattr(files.os, "replace", lambda *a: (_ for _ in ()).throw(OSError(errno.EROFS, "Read-only file system")))
    with pytest.raises(OSError, match="Read-only") as caught:
        write_json(tmp_path / "metrics.json", {"a": 1})
    assert caught.value.filename == str(tmp_path / "metrics.json")
    with pytest.raises(OSError, match="Read-only"):
        publish(own, tmp_path / "contact.npy")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["body"]
    assert [p.name for p in (tmp_path / "body").iterdir()] == ["contact.npy"]


def test_a_temporary_that_cannot_be_created_is_named_by_its_target(tmp_path, monkeypatch):
    """mkstemp refused (EACCES): the error names the file meant, not a random temporary name."""
    real_open = os.open

    def refuse(path, *args, **kwargs):
        if Path(path).parent == tmp_path:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", refuse)
    with pytest.raises(PermissionError) as caught:
        write_text(tmp_path / "config.yaml", "a: 1\n")
    assert caught.value.filename == str(tmp_path / "config.yaml")


@pytest.mark.parametrize("umask", [0o022, 0o027, 0o002])
def test_result_files_follow_the_umask(tmp_path, umask):
    """Results are 0o666 less the umask, as files opened by hand (mkstemp alone gives 0o600)."""
    old = os.umask(umask)
    try:
        write_json(tmp_path / "run.json", {})
        save_npy(tmp_path / "a.npy", np.zeros(2))
        save_npz(tmp_path / "b.npz", a=np.zeros(2))
        publish(tmp_path / "a.npy", tmp_path / "public" / "a.npy")
    finally:
        os.umask(old)
    for path in (tmp_path / "run.json", tmp_path / "a.npy", tmp_path / "b.npz", tmp_path / "public" / "a.npy"):
        assert path.stat().st_mode & 0o777 == 0o666 & ~umask, path
