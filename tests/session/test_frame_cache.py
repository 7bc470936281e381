"""The run's frame cache (`intercap.session.frame_cache`): depth and masks decoded once give exactly
what the PNGs give, unusable files stay dropped and warned about in every process, and a cache of
other files is not used."""
from pathlib import Path

import numpy as np
import pytest

from conftest import write_tiny_session
from intercap.session import Session
from intercap.session import frame_cache


def reads(session: Session) -> dict:
    """Every depth and mask read of the session, by (camera, kind, frame)."""
    out = {}
    for c in range(session.num_cameras):
        for f in session.frame_ids:
            out[(c, "depth", int(f))] = session.read_depth(c, int(f))
            for kind in ("person", "object"):
                out[(c, kind, int(f))] = session.read_mask(c, int(f), kind)
    return out


def assert_same_reads(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if a[key] is None:
            assert b[key] is None, key
        else:
            assert b[key] is not None and a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key]), key


@pytest.fixture
def session_with_a_bad_depth(tmp_path: Path) -> Path:
    """Two cameras, 4 frames; cam1's depth of frame 2 is not a PNG, and cam0 has
    no object mask for frame 3."""
    root = write_tiny_session(tmp_path / "s", num_frames=4)
    (root / "cam1" / "depth" / "000002.png").write_bytes(b"not a png")
    (root / "cam0" / "masks" / "object" / "000003.png").unlink()
    return root


def test_cached_reads_are_the_pngs_reads_and_bad_files_stay_dropped(session_with_a_bad_depth: Path, tmp_path: Path):
    out = tmp_path / "out"
    plain = Session.load(session_with_a_bad_depth)
    expected = reads(plain)
    assert expected[(1, "depth", 2)] is None and expected[(0, "object", 3)] is None  # the fixture's holes

    building = Session.load(session_with_a_bad_depth)
    assert frame_cache.build(building, out, progress=False)
    assert building.frame_cache is not None
    assert_same_reads(expected, reads(building))

    worker = frame_cache.open_session(session_with_a_bad_depth, out)  # another process's view
    assert worker.frame_cache is not None
    warned = [p for p in worker.problems if p.path == "cam1/depth/000002.png"]
    assert len(warned) == 1 and "dropped" in warned[0].message  # before any frame is read
    assert not worker.availability()["depth"][1, 2] and worker.availability()["depth"][1, 1]
    assert_same_reads(expected, reads(worker))
    assert [p for p in worker.problems if p.path == "cam1/depth/000002.png"] == warned  # not warned twice

    frame_cache.remove(out)
    assert not (out / "cache").exists()
    assert frame_cache.open_session(session_with_a_bad_depth, out).frame_cache is None


def test_a_cache_of_other_files_is_not_used(tiny_session: Path, tmp_path: Path):
    out = tmp_path / "out"
    assert frame_cache.build(Session.load(tiny_session), out, progress=False)
    depth = tiny_session / "cam0" / "depth" / "000001.png"
    import cv2

    changed = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
    changed[changed > 0] += 7  # the session's file rewritten after the cache was made
    cv2.imwrite(str(depth), changed)
    session = frame_cache.open_session(tiny_session, out)
    assert session.frame_cache is None
    assert np.array_equal(session.read_depth(0, 1), changed.astype(np.float32) / 1000)
    rebuilt = Session.load(tiny_session)
    assert frame_cache.build(rebuilt, out, progress=False)  # remade for these files
    assert np.array_equal(rebuilt.read_depth(0, 1), changed.astype(np.float32) / 1000)


def test_a_killed_build_leaves_no_cache_to_attach(tiny_session: Path, tmp_path: Path):
    out = tmp_path / "out"
    session = Session.load(tiny_session)
    assert frame_cache.build(session, out, progress=False)
    (frame_cache.cache_dir(out) / frame_cache.MANIFEST).unlink()  # the manifest is written last
    assert frame_cache.open_session(tiny_session, out).frame_cache is None
