"""anny backend (default): 13,718 vertices, 104 bones with full fingers, 52 face actions.

anny (Apache-2.0, CC0 assets) ships its model in its wheel; its first
construction builds a cache (about half a minute), later ones load it in about a
second. The cache folder is configurable (`cache_dir`, else $ANNY_CACHE_DIR,
else ~/.cache/anny).

Conventions, measured on the rest mesh: model coordinates are z-up with the
person facing -y and their left on +x; the root bone sits at the origin
(pelvis). anny's 'local-ref' pose parameters rotate each bone in axes that are
aligned with the model axes at rest, so for a standing body x is the
flexion/extension axis of spine, hips and knees (+x bends the spine forward and
the knee, -x swings the thigh forward), y abducts, z twists.
"""
from __future__ import annotations

import contextlib
import gzip
import logging
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from intercap.body_models.base import BodyModel, BodyOutput, BodyParams, axis_angle_to_matrix
from intercap.body_models.keypoints import BODY_25, FINGERS, NUM_BODY_HANDS
from intercap.body_models.regions import contact_regions, farthest_point_subsample, palm_normal

log = logging.getLogger(__name__)

SIDES = ("L", "R")
# anny finger chains: finger1 is the thumb ... finger5 the little finger.
FINGER_BONES = {finger: f"finger{k + 1}" for k, finger in enumerate(FINGERS)}
PHENOTYPES = ["gender", "age", "muscle", "weight", "height", "proportions"]
COCO_TO_BODY25 = {
    "nose": "nose", "right_shoulder": "right_shoulder", "right_elbow": "right_elbow",
    "right_wrist": "right_wrist", "left_shoulder": "left_shoulder", "left_elbow": "left_elbow",
    "left_wrist": "left_wrist", "right_hip": "right_hip", "right_knee": "right_knee",
    "right_ankle": "right_ankle", "left_hip": "left_hip", "left_knee": "left_knee",
    "left_ankle": "left_ankle", "right_eye": "right_eye", "left_eye": "left_eye",
    "right_ear": "right_ear", "left_ear": "left_ear", "left_big_toe": "left_big_toe",
    "left_small_toe": "left_small_toe", "left_heel": "left_heel", "right_big_toe": "right_big_toe",
    "right_small_toe": "right_small_toe", "right_heel": "right_heel",
}


def is_hand_bone(label: str) -> bool:
    return label.startswith(("finger", "metacarpal"))


ANNY_INTERPOLATION: list = []  # anny's own interpolation, once `build_anny` replaced it (the tests compare)


def interpolation_weights(value: torch.Tensor, anchors: torch.Tensor, extrapolate: bool = False) -> torch.Tensor:
    """anny's piecewise-linear phenotype weights, (B,) values between (n,) anchors -> (B, n): the
    two anchors around each value weighted 1 - a and a (values outside the anchors clamped unless
    `extrapolate`). Made on the anchors' device: anny's own (`linear_interpolation_coefficients`,
    which `build_anny` replaces with this) indexes with a CPU `arange`, a copy from the host on every
    GPU evaluation, which a recorded CUDA graph cannot hold. Values and gradients are anny's."""
    if not extrapolate:
        value = torch.where(value < anchors[0], anchors[0], value)
        value = torch.where(value > anchors[-1], anchors[-1], value)
    n = len(anchors)
    upper = torch.searchsorted(anchors, value.contiguous(), side="left").clamp(1, n - 1)[:, None]
    lower = upper - 1
    alpha = (value[:, None] - anchors[lower]) / (anchors[upper] - anchors[lower])
    weights = torch.zeros(len(value), n, dtype=anchors.dtype, device=anchors.device)
    return weights.scatter(1, lower, 1.0 - alpha).scatter(1, upper, alpha)


ANNY_PHENOTYPE_WEIGHTS: list = []  # anny's own `phenotype_blendshape_weights`, once replaced (the tests compare)
_PHENOTYPE_TABLES: dict = {}  # id(anchors) -> (anchors, {(labels, device, dtype): PhenotypeTable})


@dataclass(frozen=True)
class PhenotypeTable:
    """`phenotype_weights`' constants for one label set, device and dtype: the interpolated
    phenotypes' anchors side by side, padded with +inf (F, N), their ends and last index (F,), where
    each feature's value comes from (the parameter's column, or a 0.5 column appended for an
    unexposed label) and where each of anny's variations sits in the weights laid out flat."""

    anchors: torch.Tensor  # (F, N)
    first: torch.Tensor  # (F,)
    last: torch.Tensor  # (F,)
    top: torch.Tensor  # (F,) long: the last anchor's index
    offsets: torch.Tensor  # (F,) long: F * N layout of the anchors, flat
    sources: torch.Tensor  # (F + 3,) long: interpolated features, then the three races
    columns: torch.Tensor  # (V,) long: each variation in [interpolated (F * N) | races (3)]


def _phenotype_table(labels: tuple, anchors, device, dtype) -> PhenotypeTable:
    from anny.models.model_data import PHENOTYPE_VARIATIONS

    features = [f for f in PHENOTYPE_VARIATIONS if f != "race"]
    races = tuple(PHENOTYPE_VARIATIONS["race"])
    N = max(len(PHENOTYPE_VARIATIONS[f]) for f in features)
    table = torch.full((len(features), N), float("inf"), dtype=dtype, device=device)
    for i, f in enumerate(features):
        table[i, :len(PHENOTYPE_VARIATIONS[f])] = anchors[f].to(device=device, dtype=dtype)
    sizes = torch.tensor([len(PHENOTYPE_VARIATIONS[f]) for f in features], device=device)
    sources = [labels.index(k) if k in labels else len(labels) for k in (*features, *races)]
    place = {key: i * N + j for i, f in enumerate(features) for j, key in enumerate(PHENOTYPE_VARIATIONS[f])}
    place.update({key: len(features) * N + j for j, key in enumerate(races)})
    columns = [place[key] for keys in PHENOTYPE_VARIATIONS.values() for key in keys]
    long = lambda v: torch.as_tensor(v, dtype=torch.long, device=device)  # noqa: E731
    return PhenotypeTable(table, table[:, 0].clone(), table.gather(1, (sizes - 1)[:, None])[:, 0],
                          sizes - 1, long(range(0, len(features) * N, N)), long(sources), long(columns))


def phenotype_weights(phenotype_parameters: torch.Tensor, phenotype_labels: list[str], anchors,
                      stacked_phenotype_blend_shapes_mask: torch.Tensor, extrapolate: bool) -> torch.Tensor:
    """anny's `phenotype_blendshape_weights` ((B, labels) phenotypes -> (B, K) blend shape
    coefficients), every interpolated phenotype at once: anny interpolates them one after another
    and picks each variation apart (counted on the sample: 4.2 times the forward kernels), in every
    evaluation while the shape is fitted; this is 32 kernels forward and 40 backward. The same
    floating-point operations on the same numbers, so values and gradients are anny's, bit for bit
    (tested)."""
    labels = tuple(phenotype_labels)
    key = (labels, phenotype_parameters.device, phenotype_parameters.dtype)
    cache = _PHENOTYPE_TABLES.get(id(anchors))
    if cache is None or cache[0] is not anchors:
        cache = _PHENOTYPE_TABLES[id(anchors)] = (anchors, {})
    table = cache[1].get(key)
    if table is None:  # made on the first (eager) evaluation, before any recording
        table = cache[1][key] = _phenotype_table(labels, anchors, *key[1:])
    B = phenotype_parameters.shape[0]
    values = torch.cat([phenotype_parameters, phenotype_parameters.new_full((B, 1), 0.5)], 1)[:, table.sources]
    value, race = values[:, :len(table.first)], values[:, len(table.first):]
    if not extrapolate:
        value = torch.where(value < table.first, table.first, value)
        value = torch.where(value > table.last, table.last, value)
    upper = (table.anchors < value[..., None]).sum(-1).clamp(min=torch.ones_like(table.top), max=table.top)  # searchsorted, left
    lower = upper - 1
    flat = table.anchors.flatten()
    low_anchor, up_anchor = flat[lower + table.offsets], flat[upper + table.offsets]
    alpha = ((value - low_anchor) / (up_anchor - low_anchor))[..., None]
    weights = torch.zeros(*value.shape, table.anchors.shape[1], dtype=value.dtype, device=value.device)
    weights = weights.scatter(2, lower[..., None], 1.0 - alpha).scatter(2, upper[..., None], alpha)
    race = torch.nan_to_num(race / torch.sum(race, dim=1, keepdim=True), 1 / 3, 1 / 3, 1 / 3)
    phens = torch.cat([weights.flatten(1), race], 1)[:, table.columns]
    mask = stacked_phenotype_blend_shapes_mask.unsqueeze(0)
    return torch.prod(phens.unsqueeze(1) * mask + (1 - mask), dim=-1)


ANNY_LOAD_BLEND_SHAPE: list = []  # anny's own `load_blend_shape`, once `build_anny` replaced it (the tests compare)


def load_blend_shape(filename, vertices_count: int, world_transformation, dtype) -> torch.Tensor:
    """anny's `load_blend_shape` (a gzipped text file of "vertex dx dy dz" rows, in decimetres),
    parsed in one numpy pass instead of anny's per-row Python loop, where its cache build spent most
    of its time (BENCHMARKS.md). Same offsets to the bit; files it cannot read so go to anny's own."""
    with gzip.open(filename, "rt") as archive, warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "input contained no data": a few targets are empty
        rows = np.loadtxt(archive, dtype=np.float64, ndmin=2)
    ids = rows[:, 0].astype(np.int64) if rows.ndim == 2 and rows.shape[1] == 4 else None
    if ids is None or len(ids) == 0 or ids.min() < 0 or ids.max() >= vertices_count or len(np.unique(ids)) < len(ids):
        return ANNY_LOAD_BLEND_SHAPE[0](filename, vertices_count, world_transformation, dtype)
    blend_shape = torch.zeros((vertices_count, 3), dtype=dtype)
    blend_shape[torch.from_numpy(ids)] = torch.from_numpy(rows[:, 1:]).to(dtype)
    return world_transformation.apply(blend_shape)


def replace_in_anny(module, name: str, ours, originals: list) -> None:
    """Put `ours` in place of anny's `module.name` (once: a later call finds ours there), keeping
    anny's own in `originals` (the tests compare the two)."""
    original = getattr(module, name)
    if original.__module__.startswith("anny"):
        originals.append(original)
        setattr(module, name, ours)


def build_anny(cache_dir: str | os.PathLike | None, skinning: str):
    """Construct the anny model, building its cache under `cache_dir` the first time."""
    import anny
    import anny.models.full_model
    import anny.models.phenotype
    import anny.paths
    import anny.utils.interpolation

    replace_in_anny(anny.utils.interpolation, "linear_interpolation_coefficients", interpolation_weights,
                    ANNY_INTERPOLATION)
    replace_in_anny(anny.models.phenotype, "phenotype_blendshape_weights", phenotype_weights, ANNY_PHENOTYPE_WEIGHTS)
    replace_in_anny(anny.models.full_model, "load_blend_shape", load_blend_shape, ANNY_LOAD_BLEND_SHAPE)

    if cache_dir is not None:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
        anny.paths.set_anny_cache_path(cache_dir)
    cache = anny.paths.get_anny_cache_path()
    with cache_lock(cache):
        if not any(p.suffix == ".safetensors" for p in cache.glob("**/*")):
            log.warning("building the anny cache in %s (about half a minute, once)", cache)
        return anny.Anny(facial_actions="all", pose_parameterization="local-ref", skinning_method=skinning)


@contextlib.contextmanager
def cache_lock(cache: Path):
    """Hold an exclusive lock on `cache` while the model is built: anny writes its cache file in
    place, so processes starting together on a fresh machine (a run's workers, Ray tasks, test
    workers) would otherwise build it at once and one could read the other's half-written file.
    Later constructions only load (under a second each)."""
    cache.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        yield
        return
    with open(cache / ".intercap.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


class _SparseSkinning(torch.autograd.Function):
    """Linear blend skinning on the CPU, fused: the (n, J) sparse weights blend the bone transforms
    per vertex, whose columns then move the rest vertices: v = a_x x + a_y y + a_z z + t. Frames
    are the innermost axis throughout ((n, 4, 3, B) blend, (n, 3, B) rest and moved vertices), so
    every product runs over contiguous rows; the backward is written out (autograd's own went
    through a dense (n, J) weight gradient nobody asks for and a zero-filled blend per column)."""

    @staticmethod
    def forward(ctx, columns: torch.Tensor, rest: torch.Tensor, skin: "SparseSkin") -> torch.Tensor:
        J, _, _, B = columns.shape  # (J, 4, 3, B): column k of every bone's transform
        blend = (skin.weights @ columns.reshape(J, 12 * B)).view(-1, 4, 3, B)
        ctx.skin = skin
        ctx.save_for_backward(blend, rest)
        return (blend[:, 0] * rest[:, 0:1] + blend[:, 1] * rest[:, 1:2] + blend[:, 2] * rest[:, 2:3]
                + blend[:, 3])  # (n, 3, B)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        blend, rest = ctx.saved_tensors
        grad = grad.contiguous()
        n, _, B = grad.shape
        grad_blend = torch.empty(n, 4, 3, B, dtype=grad.dtype, device=grad.device)
        for k in range(3):
            torch.mul(grad, rest[:, k:k + 1], out=grad_blend[:, k])
        grad_blend[:, 3] = grad
        grad_columns = (ctx.skin.transposed @ grad_blend.view(n, 12 * B)).view(-1, 4, 3, B)
        grad_rest = None
        if ctx.needs_input_grad[1]:  # shape is being fitted: d v / d v_rest = the blended rotation
            grad_rest = torch.stack([(grad * blend[:, k]).sum(1) for k in range(3)], 1)
        return grad_columns, grad_rest, None


@dataclass(frozen=True)
class SparseSkin:
    """Skinning weights (n, J) as CSR matrices (and their transpose): a vertex moves with 2.5 of the
    104 bones on average (9 at most), so the dense product spent 97 % of its work on zeros."""

    weights: torch.Tensor  # (n, J) sparse CSR
    transposed: torch.Tensor  # (J, n) sparse CSR

    @classmethod
    def from_dense(cls, dense: torch.Tensor) -> "SparseSkin":
        with warnings.catch_warnings():  # "sparse CSR support is in beta": products with a dense matrix are all we use
            warnings.simplefilter("ignore", UserWarning)
            return cls(dense.to_sparse_csr(), dense.t().contiguous().to_sparse_csr())


def skin_vertices(skin: "torch.Tensor | SparseSkin", transforms: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning: the rest vertices (B or 1, n, 3) moved by the bone transforms
    (B, J, 3, 4) blended with the skinning weights (n, J), dense (one einsum kernel on CUDA) or
    `SparseSkin` (the CPU); (B, n, 3)."""
    B = transforms.shape[0]
    rest = rest.expand(B, *rest.shape[1:])
    if isinstance(skin, SparseSkin):
        moved = _SparseSkinning.apply(transforms.permute(1, 3, 2, 0), rest.permute(1, 2, 0).contiguous(), skin)
        return moved.permute(2, 0, 1).contiguous()  # (n, 3, B) -> (B, n, 3)
    blend = torch.einsum("nj,bjik->bnik", skin, transforms)
    # R v + t written out: a sum over a trailing axis of 3 took 7x longer
    return (blend[..., 0] * rest[..., 0:1] + blend[..., 1] * rest[..., 1:2]
            + blend[..., 2] * rest[..., 2:3] + blend[..., 3])


@dataclass
class AnnyRest:
    """The shape- and expression-dependent part of anny's forward for a set of vertices (see `AnnyBody.rest_state`)."""

    vertex_ids: torch.Tensor  # (n,)
    skin: "torch.Tensor | SparseSkin"  # (n + 10, J) skinning weights of the vertices and the ten fingertips
    bones: torch.Tensor  # (B, J, 4, 4) rest bone frames
    vertices: torch.Tensor  # (B, n + 10, 3) rest positions of the vertices and the ten fingertips
    folded_regressor: torch.Tensor  # (B, K, J', 3) the COCO regressor folded through skinning and blend shapes
    offsets: torch.Tensor  # (B, J, 4, 4) each bone's link from its parent but the pose (`AnnyBody.bone_transforms`)

    def select(self, index) -> "AnnyRest":
        return AnnyRest(self.vertex_ids, self.skin, self.bones[index], self.vertices[index], self.folded_regressor[index],
                        self.offsets[index])


class AnnyBody(BodyModel):
    name = "anny"

    def __init__(self, device="cpu", dtype=torch.float32, cache_dir=None, skinning: str = "lbs"):
        super().__init__()
        import anny

        core = build_anny(cache_dir, skinning).to(dtype=dtype)
        self.core = core
        labels = list(core.bone_labels)
        self.joint_names = labels
        self.body_joint_names = [b for b in labels[1:] if not is_hand_bone(b)]
        self.hand_joint_names = [b[:-2] for b in labels if is_hand_bone(b) and b.endswith(".L")]
        self.num_shape = len(core.phenotype_labels)
        self.num_expression = len(core.facial_action_labels)
        self.expression_names = list(core.facial_action_labels)
        index = {b: i for i, b in enumerate(labels)}
        self._index = index
        posed = [*self.body_joint_names, *(f"{h}.{side}" for side in SIDES for h in self.hand_joint_names)]
        sources = torch.zeros(len(labels), dtype=torch.long)  # 0: a zero rotation vector (the root)
        sources[[index[b] for b in posed]] = torch.arange(1, len(posed) + 1)
        self.register_buffer("pose_sources", sources)  # each bone's rotation vector in `bone_rotations`' table
        corner = torch.zeros(4, 4, dtype=dtype)
        corner[3, 3] = 1.0
        self.register_buffer("homogeneous_corner", corner)
        self.register_buffer("homogeneous_eye", torch.eye(4, dtype=dtype))
        parent = core.kinematic_chain_indices[3].clone()  # the root: itself
        self.register_buffer("bone_parent", parent)
        self.register_buffer("chain_sources", torch.cat([sources, torch.tensor([len(posed) + 1])]))  # + global_orient
        # `bone_transforms`' chain: the bones (J), the world placement above the root (J), the identity (J + 1)
        J, U, eye = len(parent), core.reference_bone_orientations, torch.eye(3, dtype=dtype)[None]
        self.register_buffer("link_left", torch.cat([U[parent].mT, eye]).contiguous())  # U_p^T, then I
        self.register_buffer("link_right", torch.cat([U, eye]).contiguous())  # U_c, then I
        step = torch.cat([parent, torch.tensor([J + 1, J + 1])])
        step[0] = J
        ancestors = []
        while bool((step[:J + 1] <= J).any()):  # 2^k-th ancestors until each lies above the placement
            ancestors.append(step)
            step = step[step]
        self.register_buffer("bone_ancestors", torch.stack(ancestors))  # (S, J + 2)
        self.register_buffer("faces", core.get_triangular_faces().long())

        coco = anny.KeypointsRegressor.coco(core)
        self._coco_labels = list(coco.labels)
        self.register_buffer("coco_weights", coco.regression_weights.to(dtype))  # (23, V)

        rest = core(None, None)
        rest_vertices = rest["vertices"][0].detach().double().cpu().numpy()
        rest_heads = rest["bone_poses"][0, :, :3, 3].detach().double().cpu().numpy()
        weights = self.dense_weights(core)  # (V, J)
        dominant = weights.argmax(1)
        self.register_buffer("fingertip_vertex_ids", self._fingertip_vertices(rest_vertices, rest_heads, dominant))
        self.up_axis = np.array([0.0, 0.0, 1.0])
        self.forward_axis = np.array([0.0, -1.0, 0.0])
        self.contact_regions = self._regions(rest_vertices, rest_heads, dominant)
        for side in SIDES:
            self.register_buffer(f"finger_flex_axes_{side}", self._flex_axes(rest_vertices, rest_heads, side))
        self.fitting_subsample = torch.from_numpy(farthest_point_subsample(rest_vertices, 2000))
        self.keypoint_valid = torch.ones(NUM_BODY_HANDS, dtype=torch.bool)
        self._build_skinned_regressor(core)
        self.to(device)

    # -- construction helpers -------------------------------------------------
    def _build_skinned_regressor(self, core) -> None:
        """Fold anny's COCO regressor through skinning and the blend shapes (see `sparse_forward`).

        A regressed keypoint is sum_v w_kv x_v with x_v = sum_j s_vj (R_j r_v + t_j) and
        r_v = r0_v + sum_a c_a D_av, so it is sum_j R_j P_kj(c) + t_j S_kj with
        P_kj(c) = sum_v w_kv s_vj (r0_v + sum_a c_a D_av) and S_kj = sum_v w_kv s_vj:
        exact, and independent of the 13,718 vertices once folded."""
        self._sparse_ok = core.bone_orientation == "cached" and core.rest_orientation_refiner is None
        if not self._sparse_ok:
            return
        weights = core.dense_vertex_bone_weights.double()  # (V, J)
        wk = self.coco_weights.double()  # (K, V)
        used = torch.nonzero(((wk.abs() > 0).double() @ (weights > 0).double()).sum(0) > 0)[:, 0]
        self.register_buffer("coco_bones", used)  # the bones any regressed keypoint depends on
        regressed = torch.nonzero(wk.abs().sum(0) > 0)[:, 0]  # the few vertices any keypoint reads
        folded = wk[:, regressed, None] * weights[None][:, regressed][..., used]  # (K, V', J')
        self.register_buffer("coco_skin", folded.sum(1).to(self.dtype))  # (K, J')
        self.register_buffer("coco_rest", torch.einsum(
            "kvj,vd->kjd", folded, core.template_vertices[regressed].double()).to(self.dtype))
        self.register_buffer("coco_blend", torch.einsum(
            "kvj,avd->akjd", folded, core.blendshapes[:, regressed].double()).to(self.dtype))  # (A, K, J, 3)
        # the blend shapes of `rest_state` as (A, ...) matrices: one matmul each
        self.register_buffer("_coco_blend_flat", self.coco_blend.flatten(1), persistent=False)
        self.register_buffer("_heads_blend", core.bone_heads_blendshapes.flatten(1).contiguous(),
                             persistent=False)
        self.register_buffer("_orientation_blend", core.bone_orientation_blendshapes.flatten(1).contiguous(),
                             persistent=False)

    @staticmethod
    def dense_weights(core) -> np.ndarray:
        ids = core.vertex_bone_indices.long().cpu().numpy()
        w = core.vertex_bone_weights.double().cpu().numpy()
        dense = np.zeros((ids.shape[0], core.bone_count))
        np.add.at(dense, (np.arange(ids.shape[0])[:, None].repeat(ids.shape[1], 1), ids), w)
        return dense

    def _fingertip_vertices(self, vertices, heads, dominant) -> torch.Tensor:
        """Per side and finger, the vertex furthest along the distal phalanx: the tip."""
        tips = []
        for side in SIDES:
            for finger in FINGERS:
                chain = FINGER_BONES[finger]
                mid, distal = self._index[f"{chain}-2.{side}"], self._index[f"{chain}-3.{side}"]
                direction = heads[distal] - heads[mid]
                candidates = np.flatnonzero(dominant == distal)
                along = (vertices[candidates] - heads[distal]) @ direction
                tips.append(int(candidates[np.argmax(along)]))
        return torch.tensor(tips)  # (10,) left thumb..little, right thumb..little

    def _flex_axes(self, vertices, heads, side) -> torch.Tensor:
        """(Jh, 3) rest-frame axis per hand bone about which a positive angle curls it towards the palm."""
        tips = self.fingertip_vertex_ids.numpy()[(0 if side == "L" else 5):][:5]
        palm = palm_normal(
            heads[self._index[f"wrist.{side}"]], heads[self._index[f"finger2-1.{side}"]],
            heads[self._index[f"finger5-1.{side}"]], side,
        )
        axes = []
        for name in self.hand_joint_names:
            head = heads[self._index[f"{name}.{side}"]]
            if name.startswith("metacarpal"):
                finger = int(name[-1]) + 1  # metacarpal k carries finger k+1
                end = heads[self._index[f"finger{finger}-1.{side}"]]
            else:
                chain, k = name.split("-")
                end = heads[self._index[f"{chain}-{int(k) + 1}.{side}"]] if k != "3" else vertices[tips[int(chain[-1]) - 1]]
            axis = np.cross(end - head, palm)
            axes.append(axis / np.linalg.norm(axis))
        return torch.tensor(np.array(axes), dtype=self.dtype)

    def curl_fingers(self, params: BodyParams, side: str, amount: torch.Tensor | float, thumb: float = 0.6) -> None:
        """Close one hand in place: `amount` in radians per finger joint (B,) or scalar; metacarpals stay."""
        axes = getattr(self, f"finger_flex_axes_{side}")  # (Jh, 3)
        amount = torch.as_tensor(amount, dtype=self.dtype, device=axes.device).reshape(-1, 1, 1)
        scale = torch.tensor(
            [0.0 if n.startswith("metacarpal") else (thumb if n.startswith("finger1") else 1.0) for n in self.hand_joint_names],
            dtype=self.dtype, device=axes.device,
        )[None, :, None]
        pose = params.left_hand_pose if side == "L" else params.right_hand_pose
        pose[:] = amount * scale * axes[None]

    def _regions(self, vertices, heads, dominant) -> dict[str, torch.Tensor]:
        def ids(predicate):
            return [i for i, b in enumerate(self.joint_names) if predicate(b)]

        groups = {}
        palms = {}
        for side in SIDES:
            groups[f"hand.{side}"] = ids(lambda b: b.endswith(f".{side}") and (is_hand_bone(b) or b.startswith("wrist")))
            groups[f"foot.{side}"] = ids(lambda b: b.endswith(f".{side}") and b.startswith(("foot", "toe")))
            groups[f"forearm.{side}"] = ids(lambda b: b.endswith(f".{side}") and b.startswith("lowerarm"))
            palms[side] = palm_normal(
                heads[self._index[f"wrist.{side}"]],
                heads[self._index[f"finger2-1.{side}"]],
                heads[self._index[f"finger5-1.{side}"]],
                side,
            )
        groups["thigh"] = ids(lambda b: b.startswith("upperleg"))
        groups["pelvis"] = ids(lambda b: b.startswith(("pelvis", "root", "spine05")))
        faces = self.faces.cpu().numpy()
        regions = contact_regions(
            vertices, faces, dominant, groups, palms,
            up=np.array([0.0, 0.0, 1.0]), forward=np.array([0.0, -1.0, 0.0]),
            hip_height=float(heads[self._index["upperleg01.L"], 2]),
            knee_height=float(heads[self._index["lowerleg01.L"], 2]),
        )
        return {name: torch.from_numpy(v) for name, v in regions.items()}

    # -- interface ----------------------------------------------------------------
    @property
    def dtype(self) -> torch.dtype:
        return self.coco_weights.dtype

    @property
    def num_vertices(self) -> int:
        return int(self.coco_weights.shape[1])

    def neutral_shape(self) -> torch.Tensor:
        return torch.full((1, self.num_shape), 0.5)

    def locate_joint(self, joint: str) -> tuple[str, int]:
        if is_hand_bone(joint):
            side = joint[-1]
            return side, self.hand_joint_names.index(joint[:-2])
        if joint not in self.body_joint_names:
            raise KeyError(f"unknown anny bone {joint!r}")
        return "body", self.body_joint_names.index(joint)

    def bone_rotations(self, params: BodyParams, with_global: bool = False) -> torch.Tensor:
        """(B, 104, 3, 3) local rotations for every bone; the root stays identity (`with_global`:
        (B, 105, 3, 3), the global orientation last). Body, hands (and global orientation) in one
        Rodrigues pass, not three with copies into place; a zero rotation vector gives the
        identity exactly."""
        pose = params.body_pose
        parts = [pose.new_zeros(pose.shape[0], 1, 3), pose, params.left_hand_pose, params.right_hand_pose]
        if with_global:
            parts.append(params.global_orient[:, None])
        sources = self.chain_sources if with_global else self.pose_sources
        return axis_angle_to_matrix(torch.cat(parts, 1).index_select(1, sources))

    def pose_matrices(self, params: BodyParams) -> torch.Tensor:
        """(B, 104, 4, 4) homogeneous `bone_rotations`."""
        return torch.nn.functional.pad(self.bone_rotations(params), (0, 1, 0, 1)) + self.homogeneous_corner

    def forward(self, params: BodyParams) -> BodyOutput:
        out = self.core(self.pose_matrices(params), phenotype_kwargs=params.shape, facial_actions=params.expression)
        vertices = out["vertices"]  # (B, V, 3) model coordinates
        joints = out["bone_poses"][..., :3, 3]  # (B, J, 3)
        coco = torch.einsum("kv,bvd->bkd", self.coco_weights, vertices)  # (B, 23, 3)
        keypoints = self._openpose_keypoints(coco, joints, vertices[:, self.fingertip_vertex_ids])
        return self.world_output(vertices, joints, keypoints, params)

    def rest_state(self, params: BodyParams, vertex_ids: torch.Tensor) -> "AnnyRest":
        """What `sparse_forward` computes from shape and expression alone (rest bone frames, rest
        vertices, the folded keypoint regressor): computed once and passed back in while shape
        and expression stay fixed, it saves about 40 % of a fitting step's forward."""
        import roma

        if not self._sparse_ok:
            return None
        core = self.core
        phenotype = core._parse_parameter_kwargs(params.shape, core.phenotype_labels, 0.5, "phenotype_kwargs")
        local_changes = core._parse_parameter_kwargs(None, core.local_change_labels, 0.0, "local_changes_kwargs")
        actions = core._parse_parameter_kwargs(params.expression, core.facial_action_labels, 0.0, "facial_actions")
        coeffs = core._get_phenotype_blendshape_coefficients(phenotype, local_changes, actions)  # (B, A)
        B = coeffs.shape[0]
        heads = core.template_bone_heads[None] + (coeffs @ self._heads_blend).view(B, -1, 3)
        cross = core.bone_template_orientation_matrices[None] + (coeffs @ self._orientation_blend).view(B, -1, 3, 3)
        rest = torch.zeros(*heads.shape[:2], 4, 4, dtype=heads.dtype, device=heads.device)
        rest[..., :3, :3] = roma.special_procrustes(cross)
        rest[..., :3, 3] = heads
        rest[..., 3, 3] = 1.0
        if core.root_identity_orientation:
            rest[:, 0, :3, :3] = torch.eye(3, dtype=heads.dtype, device=heads.device)
        ids, skin, template, blend = self._vertex_tables(vertex_ids)
        rest_vertices = template[None] + (coeffs @ blend).view(B, -1, 3)
        folded = self.coco_rest[None] + (coeffs @ self._coco_blend_flat).view(B, *self.coco_rest.shape)  # (B, K, J, 3)
        return AnnyRest(vertex_ids, skin, rest, rest_vertices, folded, self._link_offsets(rest))

    def _link_offsets(self, rest: torch.Tensor) -> torch.Tensor:
        """(B, J, 4, 4) from the rest bone frames (B, J, 4, 4): [0 | U_p^T q_c] with a 1 in the
        corner, q_c = A_p (h_c - h_p) the reference head offset from the parent p (A_p = U_p R_p^T,
        A_root = I; U the reference orientations, R, h the rest frames): what `bone_transforms`
        adds to each bone's posed rotation to link it to its parent (anny's 'local-ref' chain)."""
        R, h = rest[..., :3, :3], rest[..., :3, 3]
        parent = self.bone_parent
        A = self.core.reference_bone_orientations @ R.mT
        A = torch.cat([torch.eye(3, dtype=A.dtype, device=A.device).expand_as(A[:, :1]), A[:, 1:]], 1)
        link = self.link_left[:-1] @ A[:, parent] @ (h - h[:, parent])[..., None]  # (B, J, 3, 1)
        return torch.nn.functional.pad(link, (3, 0, 0, 1)) + self.homogeneous_corner

    def _vertex_tables(self, vertex_ids: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """`rest_state`'s gathers for `vertex_ids` and the fingertips (ids, skinning weights, template
        positions, blend shapes as an (A, n * 3) matrix), kept for the last few vertex sets asked: a
        fit asks for the same ones (its fitting vertices, all of them for E_D's normals) thousands of
        times, and the gather cost more than the blend (callers do not change vertex ids in place: a
        tensor asked before is known by identity, without reading it back from a GPU). Skinning
        weights are sparse on the CPU (CUDA keeps the dense product, which it runs in one kernel)."""
        cache = self.__dict__.setdefault("_vertex_tables_cache", [])
        for source, ids, tables in cache:  # the same tensor object first: comparing values makes a GPU wait
            if source is vertex_ids:
                return tables
        for source, ids, tables in cache:  # the same values: kept under this tensor too, found by identity next
            if ids.shape == vertex_ids.shape and torch.equal(ids, vertex_ids):
                cache.insert(0, (vertex_ids, ids, tables))
                del cache[6:]
                return tables
        core = self.core
        ids = torch.cat([vertex_ids.to(self.fingertip_vertex_ids), self.fingertip_vertex_ids])
        skin = core.dense_vertex_bone_weights[ids]
        if skin.device.type == "cpu":
            skin = SparseSkin.from_dense(skin)
        tables = (ids, skin, core.template_vertices[ids], core.blendshapes[:, ids].reshape(core.blendshapes.shape[0], -1))
        cache.insert(0, (vertex_ids, vertex_ids.clone(), tables))
        del cache[6:]
        return tables

    def sparse_forward(self, params: BodyParams, vertex_ids: torch.Tensor, rest: "AnnyRest | None" = None) -> BodyOutput:
        """`forward` for fitting: keypoints and joints exactly as `forward`, but only the vertices
        `vertex_ids` (BodyOutput.vertices is (B, len(vertex_ids), 3)). Skins those vertices only and
        takes the regressed keypoints from the folded regressor (`_build_skinned_regressor`), so a
        fitting step costs a fraction of the 13,718-vertex forward. `rest`: `rest_state` of the
        same shape, expression and vertices, when those do not change between calls."""
        if not self._sparse_ok:
            return super().sparse_forward(params, vertex_ids)
        if rest is None:
            rest = self.rest_state(params, vertex_ids)
        transforms, bone_poses = self.bone_transforms(params, rest)  # (B, J, 4, 4), in the world
        vertices = skin_vertices(rest.skin, transforms[..., :3, :], rest.vertices)  # (B, n, 3)
        used = transforms[:, self.coco_bones]
        coco = (torch.einsum("bjde,bkje->bkd", used[..., :3, :3], rest.folded_regressor)
                + torch.einsum("bjd,kj->bkd", used[..., :3, 3], self.coco_skin))
        joints = bone_poses[..., :3, 3]
        n = len(rest.vertex_ids)
        keypoints = self._openpose_keypoints(coco, joints, vertices[:, n:])
        return BodyOutput(vertices=vertices[:, :n], joints=joints, keypoints=keypoints)

    def bone_transforms(self, params: BodyParams, rest: "AnnyRest") -> tuple[torch.Tensor, torch.Tensor]:
        """anny's forward kinematics ('local-ref', `get_bone_transforms`) placed in the world:
        (B, J, 4, 4) skinning transforms T_c and posed bone frames W_c, W_c = W_p K_c with
        K_c = [U_p^T D_c U_c | U_p^T q_c] (D_c the pose's rotation; the root its own parent,
        q_root = 0, which makes K_root anny's W_root), above the root the world placement
        [global orientation | translation].

        The chain by pointer doubling: each bone's product with its 2^k-th ancestor's, five
        batched products for anny's 17 levels and the placement (anny takes one per level, and
        the placement then moved every point apart); the rest-dependent link offsets come with
        the rest state (`_link_offsets`)."""
        links = torch.nn.functional.pad(self.link_left @ self.bone_rotations(params, with_global=True)
                                        @ self.link_right, (0, 1, 0, 1))  # (B, J + 1, 4, 4)
        B = len(links)
        place = torch.nn.functional.pad(params.transl[:, None, :, None], (3, 0, 0, 1)) + self.homogeneous_corner
        chain = torch.cat([links + torch.cat([rest.offsets, place], 1), self.homogeneous_eye.expand(B, 1, 4, 4)], 1)
        for ancestors in self.bone_ancestors:  # the last row is the identity, its own ancestor
            chain = chain.index_select(1, ancestors) @ chain
        poses = chain[:, :-2]
        rotations = poses[..., :3, :3] @ rest.bones[..., :3, :3].mT  # T_c = W_c P_c^-1
        translations = poses[..., :3, 3:] - rotations @ rest.bones[..., :3, 3:]
        return torch.cat([torch.cat([rotations, translations], -1), poses[..., 3:, :]], -2), poses

    def _openpose_keypoints(self, coco: torch.Tensor, joints: torch.Tensor, tips: torch.Tensor) -> torch.Tensor:
        """(B, 67, 3) from the COCO+feet regression (B, 23, 3), bone heads (B, J, 3) and the ten
        fingertip vertices (B, 10, 3): BODY_25 from the regressor, hands from finger bones and tips.
        One gather (`_keypoint_sources`): picking the 67 one by one cost ~130 kernels a backward pass."""
        labels = self._coco_labels
        left_shoulder, right_shoulder = labels.index("left_shoulder"), labels.index("right_shoulder")
        left_hip, right_hip = labels.index("left_hip"), labels.index("right_hip")
        neck = (coco[:, left_shoulder] + coco[:, right_shoulder]) / 2
        mid_hip = (coco[:, left_hip] + coco[:, right_hip]) / 2
        sources = torch.cat([coco, joints, tips, neck[:, None], mid_hip[:, None]], dim=1)
        return sources.index_select(1, self._keypoint_sources(joints.shape[1], coco.device))

    def _keypoint_sources(self, bones: int, device: torch.device) -> torch.Tensor:
        """(67,) row of each keypoint in `_openpose_keypoints`' sources: the regressed points, the
        bone heads (the wrist's head, not the regressed surface point, so finger poses leave it
        alone), the fingertips, then the neck and the mid hip (means of the shoulders, the hips)."""
        cache = self.__dict__.setdefault("_keypoint_sources_cache", {})
        if (bones, device) not in cache:
            regressed = len(self._coco_labels)
            tips = regressed + bones
            named = {label: i for i, label in enumerate(self._coco_labels)}
            named.update(neck=tips + 10, mid_hip=tips + 11, left_wrist=regressed + self._index["wrist.L"],
                         right_wrist=regressed + self._index["wrist.R"])
            rows = [named[COCO_TO_BODY25.get(n, n)] for n in BODY_25]
            for s, side in enumerate(SIDES):
                rows.append(named["left_wrist" if side == "L" else "right_wrist"])
                for f, finger in enumerate(FINGERS):
                    rows += [regressed + self._index[f"{FINGER_BONES[finger]}-{k}.{side}"] for k in (1, 2, 3)]
                    rows.append(tips + 5 * s + f)
            cache[(bones, device)] = torch.tensor(rows, device=device)
        return cache[(bones, device)]
