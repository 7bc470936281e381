"""The animated .glb of a take, read back byte by byte as the glTF 2.0 format lays it out (no glTF
library): header, JSON chunk, binary chunk, accessors, and the animation sampled at a frame."""
from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import SAMPLE_SESSION
from scipy.spatial.transform import Rotation

from intercap.config import load_config
from intercap.pipeline import run_pipeline
from intercap.stages.export.gltf import world_to_gltf, write_glb

GT = SAMPLE_SESSION / "ground_truth"
NPM = Path(__file__).resolve().parents[2] / ".cache" / "npm" / "node_modules"  # setup.sh installs here
NAN_BODY, BAD_OBJECT = 6, 9  # frames whose body is NaN / whose object pose is marked invalid
COMPONENTS = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
DTYPES = {5126: np.float32, 5125: np.uint32}


class Glb:
    """A .glb parsed with struct and numpy: the JSON document and the accessors' arrays."""

    def __init__(self, path):
        data = path.read_bytes()
        magic, version, length = struct.unpack_from("<III", data, 0)
        assert (magic, version, length) == (0x46546C67, 2, len(data))
        json_len, json_type = struct.unpack_from("<II", data, 12)
        assert json_type == 0x4E4F534A and json_len % 4 == 0
        self.doc = json.loads(data[20:20 + json_len])
        bin_len, bin_type = struct.unpack_from("<II", data, 20 + json_len)
        assert bin_type == 0x004E4942 and 28 + json_len + bin_len == len(data)
        self.bin = data[28 + json_len:]
        assert self.doc["asset"]["version"] == "2.0" and self.doc["buffers"][0]["byteLength"] == bin_len

    def accessor(self, index: int) -> np.ndarray:
        acc = self.doc["accessors"][index]
        view = self.doc["bufferViews"][acc["bufferView"]]
        n = COMPONENTS[acc["type"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        assert start % 4 == 0 and acc["count"] * n * 4 <= view["byteLength"]
        out = np.frombuffer(self.bin, DTYPES[acc["componentType"]], acc["count"] * n, start)
        out = out.reshape(acc["count"], n) if n > 1 else out
        if "min" in acc:  # the bounds the format asks for must hold
            assert np.all(out.reshape(len(out), -1).min(0) >= np.float32(acc["min"]))
            assert np.all(out.reshape(len(out), -1).max(0) <= np.float32(acc["max"]))
        return out

    def node(self, name: str) -> tuple[int, dict]:
        return next((i, n) for i, n in enumerate(self.doc["nodes"]) if n.get("name") == name)

    def sample(self, node: int, path: str, time: float):
        """The STEP-interpolated value of a node's animated property at `time`."""
        anim = self.doc["animations"][0]
        ch = next(c for c in anim["channels"] if c["target"] == {"node": node, "path": path})
        sampler = anim["samplers"][ch["sampler"]]
        assert sampler["interpolation"] == "STEP"
        times, values = self.accessor(sampler["input"]), self.accessor(sampler["output"])
        key = max(int(np.searchsorted(times, np.float32(time), side="right")) - 1, 0)
        per_key = len(values) // len(times)
        return values.reshape(len(times), per_key, -1)[key].reshape(-1)

    def body_at(self, time: float) -> list[np.ndarray]:
        """The vertices of every body node shown at `time` (base + the weighted morph targets)."""
        shown = []
        for i, node in enumerate(self.doc["nodes"]):
            if not node.get("name", "").startswith("body_") or not self.sample(i, "scale", time).any():
                continue
            prim = self.doc["meshes"][node["mesh"]]["primitives"][0]
            w = self.sample(i, "weights", time)
            v = self.accessor(prim["attributes"]["POSITION"]).copy()
            for weight, target in zip(w, prim["targets"]):
                if weight:
                    v += weight * self.accessor(target["POSITION"])
            shown.append(v)
        return shown


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    """The sample's ground truth as a take (one failed body frame, one untrusted object pose), 4 frames
    per body mesh so the take spans several meshes."""
    verts = np.load(GT / "body_vertices.npy").astype(np.float32)
    verts[NAN_BODY] = np.nan
    poses = np.load(GT / "object_poses.npz")
    valid = np.ones(len(verts), bool)
    valid[BAD_OBJECT] = False
    import trimesh

    mesh = trimesh.load(SAMPLE_SESSION / "object.ply", process=False)
    ground = json.loads((GT / "ground.json").read_text())
    path = tmp_path_factory.mktemp("glb") / "take.glb"
    figures = write_glb(path, 5.0, np.arange(len(verts)) + 100, verts, np.load(GT / "body_faces.npy"), None,
                        mesh.vertices, mesh.faces, poses["R"], poses["t"], valid, np.load(GT / "contact.npy"),
                        ground["point"], ground["normal"], frames_per_mesh=4)
    return path, figures, verts, poses, valid, mesh


def test_glb_gives_back_each_frame(take):
    path, figures, verts, poses, valid, mesh = take
    glb = Glb(path)
    contact = np.load(GT / "contact.npy")
    T = len(verts)
    extras = glb.doc["scenes"][0]["extras"]
    assert extras["fps"] == 5.0 and extras["frame_ids"] == list(range(100, 100 + T))
    assert extras["contact"] == contact.tolist() and not extras["body_valid"][NAN_BODY]
    assert figures["glb_bytes"] == path.stat().st_size and figures["glb_body_frames"] == T - 1
    faces = np.load(GT / "body_faces.npy")
    body_meshes = [m for m in glb.doc["meshes"] if m["name"].startswith("body_")]
    assert len(body_meshes) == 8 and all(len(m["primitives"][0]["targets"]) <= 4 for m in body_meshes)
    assert np.array_equal(glb.accessor(body_meshes[0]["primitives"][0]["indices"]).reshape(-1, 3), faces)
    obj_node, _ = glb.node("object")
    free, contact_node = glb.node("object_free")[0], glb.node("object_contact")[0]
    obj_mesh = glb.doc["meshes"][glb.node("object_free")[1]["mesh"]]["primitives"][0]
    np.testing.assert_allclose(glb.accessor(obj_mesh["attributes"]["POSITION"]), mesh.vertices, atol=1e-6)
    for k in range(T):
        time = k / 5.0
        shown = glb.body_at(time)
        if k == NAN_BODY:
            assert shown == []  # a failed body fit is hidden
        else:
            assert len(shown) == 1
            np.testing.assert_allclose(shown[0], verts[k], atol=2e-7, rtol=0)  # float32 rounding at ~1 m
        q = glb.sample(obj_node, "rotation", time)
        t = glb.sample(obj_node, "translation", time)
        held = k - 1 if k == BAD_OBJECT else k  # an untrusted pose holds the last trusted one, hidden
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), poses["R"][held], atol=1e-6)
        np.testing.assert_allclose(t, poses["t"][held], atol=1e-6)
        vis = glb.sample(free, "scale", time)[0], glb.sample(contact_node, "scale", time)[0]
        expected = (0.0, 0.0) if not valid[k] else ((0.0, 1.0) if contact[k] else (1.0, 0.0))
        assert vis == expected, (k, vis)
    # the root turns the floor normal (world +z here) to glTF's +y
    root = glb.node("world")[1]
    M = np.asarray(root["matrix"]).reshape(4, 4).T
    np.testing.assert_allclose(M @ [0, 0, 1, 0], [0, 1, 0, 0], atol=1e-12)
    assert glb.doc["scenes"][0]["nodes"] == [glb.node("world")[0]]


def test_world_to_gltf_puts_any_floor_level():
    n = np.array([0.1, -0.98, 0.15])
    p = np.array([0.3, 1.1, -0.4])
    M = world_to_gltf(p, n)
    np.testing.assert_allclose(M[:3, :3] @ (n / np.linalg.norm(n)), [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(M @ np.r_[p, 1], [0, 0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(M[:3, :3] @ M[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(world_to_gltf(p, [0, -1, 0])[:3, :3] @ [0, -1, 0], [0, 1, 0], atol=1e-12)
    assert np.array_equal(world_to_gltf(None, None), np.eye(4))


def _gt_results(out):
    out.mkdir(parents=True)
    for name in ("body_vertices.npy", "body_faces.npy", "object_poses.npz", "contact.npy"):
        shutil.copy(GT / name, out / name)
    (out / "prepare").mkdir()
    shutil.copy(GT / "ground.json", out / "prepare" / "ground.json")
    return out


def test_export_stage_writes_the_glb(tmp_path):
    """The export stage writes OUT/export/<session>.glb by default, and not with export.glb=false."""
    out = _gt_results(tmp_path / "out")
    metrics = run_pipeline(SAMPLE_SESSION, out, load_config(None, ["export.meshes=false"]), stages=["export"],
                           progress=False)["export"]
    path = out / "export" / "sample.glb"
    assert metrics["glb"] == str(path) and path.is_file()
    glb = Glb(path)
    verts = np.load(GT / "body_vertices.npy")
    np.testing.assert_allclose(glb.body_at(15 / 5.0)[0], verts[15], atol=2e-7, rtol=0)
    faces = np.load(GT / "body_faces.npy")
    import trimesh

    obj = trimesh.load(SAMPLE_SESSION / "object.ply", process=False)
    fixed = verts[0].nbytes + faces.size * 4 + (obj.vertices.size + obj.faces.size) * 4  # a base mesh per 64 frames
    assert verts.nbytes < path.stat().st_size < verts.nbytes + fixed + 30_000  # float32: T * V * 12 bytes, little more
    off = _gt_results(tmp_path / "off")
    run_pipeline(SAMPLE_SESSION, off, load_config(None, ["export.meshes=false", "export.glb=false"]),
                 stages=["export"], progress=False)
    assert (off / "export" / "sample.npz").is_file() and not (off / "export" / "sample.glb").exists()


VALIDATE = """const validator = require(process.argv[2]);
const fs = require('fs');
(async () => {
  const out = {};
  for (const path of process.argv.slice(3)) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(path)));
    out[path] = {errors: report.issues.numErrors, warnings: report.issues.numWarnings,
                 messages: report.issues.messages.slice(0, 5).map((m) => m.code + ' ' + (m.pointer || ''))};
  }
  console.log(JSON.stringify(out));
})();
"""


@pytest.mark.skipif(shutil.which("node") is None or not (NPM / "gltf-validator").is_dir(),
                    reason="needs node and gltf-validator (setup.sh installs it)")
def test_glb_passes_the_khronos_validator(take, tmp_path):
    """The Khronos glTF validator finds no error and no warning: the take, a body-only one, an
    object-only one, and one where every fit failed."""
    import trimesh

    path, _, verts, poses, _, _ = take
    faces = np.load(GT / "body_faces.npy")
    mesh = trimesh.load(SAMPLE_SESSION / "object.ply", process=False)
    body_only, object_only, failed = (tmp_path / f"{n}.glb" for n in ("body", "object", "failed"))
    write_glb(body_only, 30.0, [4, 5], verts[:2], faces)
    write_glb(object_only, 30.0, [0, 1, 2], object_vertices=mesh.vertices, object_faces=mesh.faces,
              R=poses["R"][:3], t=poses["t"][:3])
    write_glb(failed, 30.0, [0], np.full((1, 5, 3), np.nan, np.float32), faces[:2] % 5, R=np.full((1, 3, 3), np.nan),
              t=np.zeros((1, 3)), object_vertices=mesh.vertices, object_faces=mesh.faces)
    script = tmp_path / "validate.cjs"
    script.write_text(VALIDATE)
    run = subprocess.run(["node", str(script), str(NPM / "gltf-validator"), *map(str, (path, body_only, object_only,
                                                                                       failed))],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    reports = json.loads(run.stdout)
    assert len(reports) == 4
    for name, report in reports.items():
        assert report["errors"] == 0 and report["warnings"] == 0, (name, report)


BLENDER_SCRIPT = """
import json, sys
import numpy
numpy.bool = bool  # Debian's Blender 3.4 glTF importer still uses numpy's removed alias
import bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=sys.argv[-2])
scene = bpy.context.scene
out = {}
for frame in (0, 15):
    scene.frame_set(1 + round(frame / 5.0 * scene.render.fps))  # the importer keys seconds at the scene's rate
    graph = bpy.context.evaluated_depsgraph_get()
    shown = [o for o in scene.objects if o.name.startswith("body_") and o.matrix_world.to_scale().length > 0.5]
    body = shown[0].evaluated_get(graph)
    mesh = body.to_mesh()
    out[frame] = {"shown": [o.name for o in shown], "vertex0": list(body.matrix_world @ mesh.vertices[0].co),
                  "object": list(scene.objects["object"].matrix_world.translation),
                  "contact": scene.objects["object_contact"].matrix_world.to_scale().length > 0.5}
json.dump(out, open(sys.argv[-1], "w"))
"""


@pytest.mark.skipif(shutil.which("blender") is None, reason="needs Blender (apt-get install blender python3-numpy)")
def test_glb_opens_in_blender(take, tmp_path):
    """Blender's own glTF importer: frame 15 shows its body and object where the results put them, in
    the results' world frame (the root's floor-to-+Y turn and Blender's +Y-to-+Z turn cancel here)."""
    path, _, verts, poses, _, _ = take
    script, result = tmp_path / "import.py", tmp_path / "blender.json"
    script.write_text(BLENDER_SCRIPT)
    run = subprocess.run(["blender", "-b", "--factory-startup", "-noaudio", "--python", str(script), "--", str(path),
                          str(result)], capture_output=True, text=True, timeout=300)
    assert result.is_file(), run.stdout[-2000:] + run.stderr[-2000:]
    seen = json.loads(result.read_text())
    contact = np.load(GT / "contact.npy")
    for k in (0, 15):
        got = seen[str(k)]
        assert got["shown"] == [f"body_{100 + k // 4 * 4:06d}"], got
        np.testing.assert_allclose(got["vertex0"], verts[k, 0], atol=1e-5)
        np.testing.assert_allclose(got["object"], poses["t"][k], atol=1e-5)
        assert got["contact"] == bool(contact[k])
