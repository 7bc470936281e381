"""One configuration tree for the whole pipeline: its assembly, overrides and validation.

Each stage's section is a dataclass beside the stage, in ``intercap/stages/<stage>/config.py``:
``prepare`` (PrepareConfig), ``detect`` (DetectConfig), ``object`` (ObjectConfig), ``body``
(BodyConfig), ``contact`` (ContactConfig), ``global`` (GlobalConfig, in ``stages/global_fit``),
``physics`` (PhysicsConfig) and ``export`` (ExportConfig). The sections that are no stage live
here: ``body_model``, ``report`` and ``run``. Defaults are the dataclasses'; a YAML file and
``section.key=value`` overrides from the command line change them; every results folder gets the
tree it was produced with (``OUT/config.yaml``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from intercap.stages.prepare.config import PrepareConfig
from intercap.stages.detect.config import DetectConfig
from intercap.stages.object.config import ObjectConfig
from intercap.stages.body.config import BodyConfig
from intercap.stages.global_fit.config import GlobalConfig
from intercap.stages.contact.config import ContactConfig
from intercap.stages.physics.config import PhysicsConfig
from intercap.stages.export.config import ExportConfig


@dataclass
class BodyModelConfig:
    """Which body model, and where its files and caches are."""

    name: str = "anny"  # "anny" (default, ships with its package) or "smplx"
    cache_dir: str | None = None  # anny's cache folder; None: $ANNY_CACHE_DIR or ~/.cache/anny
    smplx_model_dir: str | None = None  # folder holding SMPLX_NEUTRAL.npz etc. (smplx only)
    dtype: str = "float32"  # the model's tensors, a torch dtype name: float32 or float64


@dataclass
class ReportConfig:
    """Mesh overlays and the HTML report written at the end of `intercap run`."""

    enabled: bool = True  # `intercap run` writes OUT/report/index.html after the stages
    overlay_stages: list[str] = field(default_factory=lambda: ["object", "body", "global"])  # stages drawn over images
    overlay_every: int = 10  # mesh overlays of every n-th frame, in every view
    alpha: float = 0.6  # opacity (0..1) of the rendered meshes over the colour images
    video: bool = True  # a video of one camera over the whole sequence (the last stage that ran)
    video_camera: str = ""  # camera name for the video; "" = the first camera
    # vp9 (WebM: plays in every browser) or h264 (MP4: needs a browser with proprietary codecs)
    video_codec: str = "vp9"
    thumbnail_width: int = 200  # pixels; thumbnails are embedded, the full images sit beside the page
    heatmap_distance_m: float = 0.02  # contact heat map: a vertex this close (m) to the object touches it
    points_per_view: int = 300  # depth points per view for the cloud-to-fit curves
    max_frames: int = 600  # geometric per-frame curves use at most this many frames, evenly spread


@dataclass
class RunConfig:
    """What `intercap run` does."""

    stages: list[str] = field(default_factory=list)  # stages to run (in pipeline order); empty: every built stage
    device: str = "cpu"  # torch device for the fits: cpu, cuda or cuda:N
    force: bool = False  # recompute stages whose output is already saved
    # processes the fitting stages cut a take into (0: one per CPU core; on a GPU, one; N > 1 share it)
    workers: int = 0
    min_frames_per_worker: int = 48  # a take shorter than twice this runs in one process
    dense_fps: float = 20.0  # sessions at this frame rate (Hz) and above take the *_dense settings (`resolved`)
    deterministic: bool = True  # on the CPU the same numbers every run (`parallel.repeatable`)
    frame_cache: bool = True  # decode depth and masks once a run into OUT/cache/frames/ (`session.frame_cache`)


@dataclass
class Config:
    """The whole tree: one section per stage (each defined beside its stage, `intercap/stages/<stage>/config.py`)
    and the three that are not stages (body model, report, run). This module only assembles and validates it."""

    body_model: BodyModelConfig = field(default_factory=BodyModelConfig)
    prepare: PrepareConfig = field(default_factory=PrepareConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)
    object: ObjectConfig = field(default_factory=ObjectConfig)
    body: BodyConfig = field(default_factory=BodyConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)
    global_: GlobalConfig = field(default_factory=GlobalConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    export: ExportConfig = field(default_factory=ExportConfig)
    report: ReportConfig = field(default_factory=ReportConfig)
    run: RunConfig = field(default_factory=RunConfig)


class ConfigError(ValueError):
    """A YAML file or override names a key that does not exist or has a bad value."""


def _coerce(value: Any, current: Any, key: str) -> Any:
    """Parse a command-line string into the type of the field it overrides."""
    if not isinstance(value, str):
        return value
    try:
        parsed = yaml.safe_load(value)
    except yaml.YAMLError as exc:
        reason = getattr(exc, "problem", None) or type(exc).__name__
        raise ConfigError(f"{key}: {value!r} is not a value ({reason}); quote it in YAML") from None
    if current is None or parsed is None:
        return parsed
    if isinstance(current, bool):
        if not isinstance(parsed, bool):
            raise ConfigError(f"{key}: expected true/false, got {value!r}")
        return parsed
    if isinstance(current, float) and isinstance(parsed, str):
        try:
            parsed = float(parsed)  # YAML reads 3e7 (no dot, no sign) as a string
        except ValueError:
            pass
    if isinstance(current, (int, float)) and not isinstance(parsed, (int, float)):
        raise ConfigError(f"{key}: expected a number, got {value!r}")
    if isinstance(current, float):
        return float(parsed)
    if isinstance(current, list) and isinstance(parsed, str):
        return [p.strip() for p in parsed.split(",") if p.strip()]
    return parsed


# Variants of a setting: `name_dense` takes the place of `name` for sessions at `run.dense_fps` and
# above, `name_gpu` on a CUDA device (`resolved`).
VARIANTS = ("dense", "gpu")


def variant_settings(section) -> list[tuple[str, str, str]]:
    """(setting, its variant's field, variant) of every `<setting>_<variant>` field of a section."""
    names = {f.name for f in dataclasses.fields(section)}
    return [(name[:-len(v) - 1], name, v) for name in sorted(names) for v in VARIANTS
            if name.endswith("_" + v) and name[:-len(v) - 1] in names]


def resolved(cfg: Config, fps: float) -> Config:
    """The settings a session at `fps` runs with on `run.device`: each setting with a variant that
    applies replaced by it. Dense: frames close in time start their fits near the answer (the
    previous frame's object pose, the previous batch's body, the per-frame results), so fewer steps
    reach the same place; sparse takes keep the full budgets. GPU: a step costs its kernel launches,
    not its size, so larger batches, windows and more chunks side by side cost about the same. The
    stages read the plain settings only; OUT/config.yaml keeps the tree as given."""
    applies = {"dense": fps >= cfg.run.dense_fps, "gpu": str(cfg.run.device).startswith("cuda")}
    sections = {}
    for f in dataclasses.fields(cfg):
        section = getattr(cfg, f.name)
        swaps = {setting: getattr(section, twin) for setting, twin, v in variant_settings(section) if applies[v]}
        if swaps:
            sections[f.name] = dataclasses.replace(section, **swaps)
    return dataclasses.replace(cfg, **sections)


# Settings with a fixed set of values, checked when the config is read (not when a stage reaches them).
LINE_SEARCHES = ("auto", "strong_wolfe", "armijo")  # `optim.minimise`'s
CHOICES = {("body", "line_search"): LINE_SEARCHES, ("global_", "line_search"): LINE_SEARCHES,
           ("prepare", "calib_refine"): ("auto", "always", "never")}

# Counts, strides and sizes a stage divides by, steps by or allocates: 0 or less is refused when read
# (rather than `step must be nonzero` or a modulo by zero halfway through a run).
POSITIVE = {
    "prepare": ("pixel_stride", "voxel_size_m", "ground_frames", "plane_iterations"),
    "detect": ("crop_size_px",),
    "object": ("crop_size", "checkpoint_every", "voxel_size_m", "overlay_every"),
    "body": ("batch_frames", "batch_frames_gpu", "overlay_every"),
    "global_": ("window_frames", "window_frames_gpu", "sdf_resolution", "sdf_cell_m"),
    "report": ("overlay_every", "thumbnail_width", "max_frames"),
    "run": ("min_frames_per_worker",),
}
NON_NEGATIVE = {"prepare": ("calib_frames", "calib_refine_frames"), "run": ("workers",)}
# Pairs of settings that bound a range: (section, lower, upper), the lower below the upper.
ORDERED = (("prepare", "depth_min_m", "depth_max_m"),)


def check_ordered(cfg: "Config") -> None:
    """A ConfigError when a range's lower bound is not below its upper one (`ORDERED`)."""
    for section, lower, upper in ORDERED:
        node = getattr(cfg, section)
        if not getattr(node, lower) < getattr(node, upper):
            raise ConfigError(f"{section}.{lower} ({getattr(node, lower)!r}) must be below "
                              f"{section}.{upper} ({getattr(node, upper)!r})")


def check_range(section: str, key: str, path: str, value: Any) -> None:
    """A ConfigError for a number below what the setting allows (`POSITIVE`, `NON_NEGATIVE`)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    if key in POSITIVE.get(section, ()) and not value > 0:
        raise ConfigError(f"{path}: must be greater than 0, got {value!r}")
    if key in NON_NEGATIVE.get(section, ()) and not value >= 0:
        raise ConfigError(f"{path}: must be 0 or more, got {value!r}")


# Sections whose name is a Python keyword: written `global` in YAML and overrides.
KEYWORD_SECTIONS = {"global": "global_"}


def _apply(node: Any, updates: dict, prefix: str = "", section: str = "") -> None:
    names = {f.name for f in dataclasses.fields(node)}
    for key, value in updates.items():
        path = f"{prefix}{key}"
        key = KEYWORD_SECTIONS.get(key, key) if not prefix else key
        if key not in names:
            raise ConfigError(f"unknown config key {path!r}; known here: {sorted(names)}")
        current = getattr(node, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ConfigError(f"{path} is a section; give it a mapping")
            _apply(current, value, prefix=path + ".", section=key)
        else:
            value = _coerce(value, current, path)
            allowed = CHOICES.get((section, key))
            if allowed and value not in allowed:
                raise ConfigError(f"{path}: expected one of {', '.join(allowed)}, got {value!r}")
            check_range(section, key, path, value)
            setattr(node, key, value)


def load_config(yaml_path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults, then the YAML file, then ``section.key=value`` overrides (``key=value`` for the
    `run` section's settings: ``device=cuda``)."""
    cfg = Config()
    if yaml_path is not None:
        try:
            data = yaml.safe_load(Path(yaml_path).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"cannot read config {yaml_path}: {exc}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"{yaml_path}: top level must be a mapping")
        _apply(cfg, data)
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override {item!r} is not of the form section.key=value")
        dotted, value = item.split("=", 1)
        *sections, leaf = dotted.strip().split(".")
        if not sections and leaf in {f.name for f in dataclasses.fields(RunConfig)}:
            sections = ["run"]  # a bare key names a `run` setting: `--set device=cuda`
        nested: dict = {leaf: value}
        for section in reversed(sections):
            nested = {section: nested}
        _apply(cfg, nested)
    check_ordered(cfg)
    return cfg


def config_to_dict(cfg: Config) -> dict:
    spelled = {field: name for name, field in KEYWORD_SECTIONS.items()}
    return {spelled.get(k, k): v for k, v in dataclasses.asdict(cfg).items()}


def save_config(cfg: Config, path: str | Path) -> None:
    from intercap.io.files import write_text

    write_text(path, yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
