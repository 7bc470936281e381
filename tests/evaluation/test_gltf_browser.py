"""The animated .glb opened the way a person does: three.js's GLTFLoader in headless Chromium, the
take played to two frames, each frame shot and checked against where the results put the body and
the object. three.js comes from npm at set-up (setup.sh, into .cache/npm); without it, or without
Chromium, the test skips. The screenshots stay in the test's tmp folder for a person to open."""
from __future__ import annotations

import functools
import http.server
import json
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from cdp_browser import Browser, find_chromium
from conftest import SAMPLE_SESSION

from intercap.stages.export.gltf import world_to_gltf, write_glb

THREE = Path(__file__).resolve().parents[2] / ".cache" / "npm" / "node_modules" / "three"
GT = SAMPLE_SESSION / "ground_truth"
FRAMES = (3, 15)  # the box on the floor, then carried (contact: the box turns red)
WIDTH, HEIGHT, FOV_DEG = 640, 480, 45.0
BACKGROUND = (16, 16, 16)

PAGE = """<!DOCTYPE html><html><head><meta charset="utf-8"><link rel="icon" href="data:,">
<style>body{margin:0;background:#000}</style>
<script type="importmap">{"imports": {"three": "./three/build/three.module.js",
 "three/addons/": "./three/examples/jsm/"}}</script></head><body>
<script type="module">
import * as THREE from 'three';
import {GLTFLoader} from 'three/addons/loaders/GLTFLoader.js';
const view = %(view)s;
const renderer = new THREE.WebGLRenderer({antialias: false, preserveDrawingBuffer: true});
renderer.setSize(view.width, view.height);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color().setRGB(...view.background.map((c) => c / 255), THREE.SRGBColorSpace);
scene.add(new THREE.AmbientLight(0xffffff, 1.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.5);
sun.position.set(...view.position);
scene.add(sun);
const camera = new THREE.PerspectiveCamera(view.fov, view.width / view.height, 0.05, 100);
camera.position.set(...view.position);
camera.lookAt(...view.target);
new GLTFLoader().load('take.glb', (gltf) => {
  scene.add(gltf.scene);
  const mixer = new THREE.AnimationMixer(gltf.scene);
  const action = mixer.clipAction(gltf.animations[0]);
  action.setLoop(THREE.LoopOnce);
  action.clampWhenFinished = true;
  action.play();
  window.showTime = (t) => { mixer.setTime(t); renderer.render(scene, camera); return true; };
  window.loaded = {fps: gltf.scene.userData.fps, clips: gltf.animations.length,
                   duration: gltf.animations[0].duration};
}, undefined, (err) => { console.error('glb: ' + err); });
</script></body></html>
"""

needs_browser = pytest.mark.skipif(find_chromium() is None or not (THREE / "build" / "three.module.js").is_file(),
                                   reason="needs chromium and three.js (setup.sh installs both)")


def silhouette(points: np.ndarray, faces: np.ndarray, position, target) -> np.ndarray:
    """(H, W) bool: triangles (glTF coordinates) as the page's camera (three.js, y up) sees them."""
    position, target = np.asarray(position, float), np.asarray(target, float)
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = points - position
    z = rel @ forward
    f = (HEIGHT / 2) / np.tan(np.radians(FOV_DEG) / 2)
    px = np.stack([WIDTH / 2 + f * (rel @ right) / z, HEIGHT / 2 - f * (rel @ up) / z], axis=1)
    mask = np.zeros((HEIGHT, WIDTH), np.uint8)
    cv2.fillPoly(mask, list(np.round(px[faces] - 0.5).astype(np.int32)), 1)
    return mask.astype(bool)


def _serve(folder: Path):
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(folder))
    handler.log_message = lambda *a, **k: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


@needs_browser
def test_glb_plays_in_three_js(tmp_path):
    import trimesh

    verts = np.load(GT / "body_vertices.npy")
    faces = np.load(GT / "body_faces.npy")
    poses = np.load(GT / "object_poses.npz")
    contact = np.load(GT / "contact.npy")
    mesh = trimesh.load(SAMPLE_SESSION / "object.ply", process=False)
    ground = json.loads((GT / "ground.json").read_text())
    site = tmp_path / "site"
    site.mkdir()
    (site / "three").symlink_to(THREE)
    write_glb(site / "take.glb", 5.0, np.arange(len(verts)), verts, faces, None, mesh.vertices, mesh.faces,
              poses["R"], poses["t"], None, contact, ground["point"], ground["normal"], frames_per_mesh=8)
    M = world_to_gltf(ground["point"], ground["normal"])  # the root node's turn: world z up -> glTF y up

    def to_gltf(x):
        return x @ M[:3, :3].T + M[:3, 3]

    centre = to_gltf(verts[list(FRAMES)].reshape(-1, 3)).mean(0)
    position = centre + np.array([0.4, 1.2, 4.2])
    view = {"width": WIDTH, "height": HEIGHT, "fov": FOV_DEG, "position": position.tolist(),
            "target": centre.tolist(), "background": BACKGROUND}
    (site / "index.html").write_text(PAGE % {"view": json.dumps(view)})
    server = _serve(site)
    shots = {}
    try:
        with Browser(WIDTH, HEIGHT) as browser:
            browser.open(f"http://127.0.0.1:{server.server_address[1]}/index.html")
            assert browser.wait_for("window.loaded !== undefined", 60), (browser.errors, browser.messages[-5:])
            loaded = browser.evaluate("window.loaded")
            for k in FRAMES:
                browser.evaluate(f"window.showTime({(k + 0.5) / 5.0})")  # mid-frame, as playback shows it
                shots[k] = cv2.imread(str(browser.screenshot(tmp_path / f"glb_frame{k:02d}.png")))[..., ::-1]
            errors = list(browser.errors)
    finally:
        server.shutdown()
    print(f"glb screenshots: {', '.join(str(tmp_path / f'glb_frame{k:02d}.png') for k in FRAMES)}")
    assert not errors, errors
    assert loaded["fps"] == 5.0 and loaded["clips"] == 1 and abs(loaded["duration"] - 29 / 5.0) < 1e-5
    for k, image in shots.items():
        obj = silhouette(to_gltf(mesh.vertices @ poses["R"][k].T + poses["t"][k]), mesh.faces, position, centre)
        body = silhouette(to_gltf(verts[k]), faces, position, centre)
        kernel = np.ones((5, 5), np.uint8)
        # inside each silhouette, away from the other's (a hand in front of the box, the box before the body)
        obj_in = cv2.erode(obj.astype(np.uint8), kernel).astype(bool) & ~cv2.dilate(body.astype(np.uint8),
                                                                                    kernel).astype(bool)
        body_in = cv2.erode(body.astype(np.uint8), kernel).astype(bool) & ~cv2.dilate(obj.astype(np.uint8),
                                                                                      kernel).astype(bool)
        outside = ~cv2.dilate((obj | body).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        rgb = image.astype(int)
        background = (np.abs(rgb - BACKGROUND).max(-1) <= 3)
        r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
        blue, red = (b - r > 40) & (b - g > 20), (r - g > 60) & (r - b > 60)
        grey = ~background & (np.abs(r - g) < 25) & (np.abs(g - b) < 25)
        obj_hue = red if contact[k] else blue
        print(f"frame {k}: object hue on {obj_hue[obj_in].mean():.0%} of the object ({obj_in.sum()} px), "
              f"grey on {grey[body_in].mean():.0%} of the body ({body_in.sum()} px), "
              f"background on {background[outside].mean():.1%} of the rest")
        assert obj_in.sum() > 100 and body_in.sum() > 1000
        assert obj_hue[obj_in].mean() > 0.8, f"frame {k}: the object's colour is missing where the object is"
        assert grey[body_in].mean() > 0.8, f"frame {k}: the body is missing where the body is"
        assert background[outside].mean() > 0.99, f"frame {k}: something drawn where nothing should be"
    a, b = (shots[k].astype(int) for k in FRAMES)
    assert (np.abs(a - b).max(-1) > 30).mean() > 0.01, "the two frames look the same"
