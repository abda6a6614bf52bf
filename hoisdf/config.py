"""Training settings: the ``[model]``, ``[train]``, ``[augment]`` and ``[loss]`` sections of ``pipelines/<name>.toml``.

Same file and override syntax as the build (``section.key=value``, values parsed as TOML). Only the
trainer and the evaluator read these dataclasses; they pass explicit values to the model, the loss,
the augmentation and the data pipeline.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import ClassVar

from hoidata.errors import DataError
from hoidata.sections import (
    apply_overrides,
    check_sections,
    current_names,
    origin,
    read_pipeline,
    refuse_renamed,
    refuse_unused,
    resolve_pipeline,
    section,
    section_names,
    toml_value,
)
from hoisdf.data.augment import AugmentSettings
from hoisdf.data.loader import SHUFFLES
from hoisdf.model.encoding import PIXEL_CONVENTIONS


@dataclass(frozen=True)
class ModelSettings:
    """Constructor arguments of :class:`hoisdf.model.HOISDF` (defaults: the paper's DexYCB model)."""

    depth: int = 50  # ResNet depth: 18, 34 or 50
    decoder: str = "small"  # U-Net decoder: "small" (DexYCB settings) or "big" (HO-3D setting)
    weights: str = ""  # backbone init: "" random, "imagenet" (torch hub cache, never downloaded) or a .pth path
    normalize_input: bool = True  # ImageNet mean/std inside the model (the reference feeds raw [0, 1])
    freeze_bn_affine: bool = True  # keep the backbone's BatchNorm scale and shift fixed (as the reference)
    channels_last: bool = False  # NHWC convolution layout (same numbers; see bench/bench_train_step.py)
    image_size: int = 256  # px: side of the network input crop
    sdf_scale: float = 3.1  # metres -> the decoders' scaled units (the reference's 3.1)
    sdf_clamp: float = 0.15  # scaled units
    n_freq: int = 5  # frequencies of the Fourier positional code of each point
    d_model: int = 256  # width of the transformer tokens
    heads: int = 4  # attention heads of every transformer layer
    ff: int = 1024  # hidden width of the transformer feed-forward layers
    dropout: float = 0.1  # dropout in the transformers
    hand_layers: int = 6  # hand transformer encoder layers
    decoder_layers: int = 4  # MANO query decoder layers
    object_layers: int = 3  # object transformer encoder layers
    sdf_features: int = 256  # width of the pixel-aligned feature entering the SDF decoders
    sdf_hidden: int = 512  # must exceed sdf_features + 33 (DeepSDF skip connection)
    sdf_dropout: float = 0.2  # dropout in the SDF decoders
    token_hidden: tuple[int, ...] = (1024, 512, 256)  # hidden widths of the pixel feature -> token MLP
    hand_queries: int = 600  # query points of the hand field passed to the pose stage (was n_hand)
    object_queries: int = 200  # query points of the object field passed to the pose stage (was n_object)
    grid_resolution: int = 64  # inference grid: resolution^3 points around the hand root and the object centre
    sheared_grid: bool = False  # reproduce the reference's sheared inference lattice
    fixed_shape: bool = False  # field-guided sampling over the whole grid, boxes as masks (torch.compile, CUDA graphs)
    sampling: str = "absolute"  # absolute | signed | random | gradient
    feature_augmentation: str = "density"  # density | none | density_concat | distance_concat
    cross_field: str = "sdf"  # sdf | none | image | target
    pose_regressor: str = "mano"  # mano | mano_only | voting | ik
    density_sign: str = "paper"  # paper: sigmoid(-d/a)/a; code: sigmoid(+d/a)/a (released checkpoints)
    beta_init: float = 0.1  # initial width of the SDF -> density conversion (scaled units, learned)
    beta_min: float = 2e-3  # lower bound of that learned width
    object_rotation: str = "chordal"  # chordal (rotation mean) | axis_angle (reference: mean of axis-angles)
    test_boxes: str = "gt"  # gt (published protocol) | predicted (from the predicted masks)
    mask_threshold: float = 0.5  # probability above which a predicted mask pixel counts (test_boxes = predicted)
    chunk: int = 32768  # grid points per SDF-decoder call at inference
    cls_dist: float = 0.04  # m: voting classification radius
    pixel_convention: str = "centers"  # centers (align_corners=False) | upstream (released code: align_corners=True)
    rot6d: str = "offset"  # offset: 6D code = identity + head output (a flat hand at init) | raw: upstream's raw code
    beta_floor: str = "clamp"  # clamp: beta_min applied in the forward | project: the parameter itself (upstream)
    field_density: str = "fresh"  # field-guided tokens' SDF: fresh (a second pass) | ranking (upstream: the ranking's)
    LIMITS: ClassVar[dict] = {
        "image_size": (">= 32",), "sdf_scale": ("> 0",), "sdf_clamp": ("> 0",), "n_freq": (">= 0",),
        **{k: (">= 1",) for k in ("d_model", "heads", "ff", "hand_layers", "decoder_layers", "object_layers",
                                  "sdf_features", "sdf_hidden", "token_hidden", "hand_queries", "object_queries",
                                  "chunk")},
        "dropout": (">= 0", "< 1"), "sdf_dropout": (">= 0", "< 1"), "grid_resolution": (">= 2",),
        "beta_init": ("> 0",), "beta_min": ("> 0",), "mask_threshold": ("> 0", "< 1"), "cls_dist": ("> 0",)}
    CHOICES: ClassVar[dict] = {
        "sampling": ("absolute", "signed", "random", "gradient"),
        "feature_augmentation": ("density", "none", "density_concat", "distance_concat"),
        "cross_field": ("sdf", "none", "image", "target"),
        "pose_regressor": ("mano", "mano_only", "voting", "ik"),
        "density_sign": ("paper", "code"),
        "object_rotation": ("chordal", "axis_angle"),
        "test_boxes": ("gt", "predicted"),
        "pixel_convention": tuple(PIXEL_CONVENTIONS),
        "rot6d": ("offset", "raw"),
        "beta_floor": ("clamp", "project"),
        "field_density": ("fresh", "ranking")}
    # old name -> new name: refused in a file or an override, read silently from a checkpoint's stored config
    RENAMED: ClassVar[dict] = {"n_hand": "hand_queries", "n_object": "object_queries"}
    POINT_DIM: ClassVar[int] = 33  # xyz (3) + Fourier code (30) of every transformer token


def model_problem(s: ModelSettings) -> tuple[str, str] | None:
    """(key, what is wrong) for the first model setting outside its choices or not fitting the others, else None."""
    for name, allowed in s.CHOICES.items():
        if getattr(s, name) not in allowed:
            return name, f"must be one of {allowed}, got {getattr(s, name)!r}"
    dim = s.POINT_DIM
    if not all(int(w) > 0 for w in s.token_hidden):
        return "token_hidden", f"must be positive layer widths, got {list(s.token_hidden)}"
    if 6 * s.n_freq + 3 != dim:
        return "n_freq", f"must be 5 (tokens carry a {dim}-dim point code), got {s.n_freq}"
    if s.d_model <= dim + 1 or s.d_model % s.heads:
        return "d_model", (f"must exceed {dim + 1} (a token holds the {dim}-dim point code) "
                           f"and be a multiple of model.heads ({s.heads}), got {s.d_model}")
    if s.sdf_hidden <= s.sdf_features + dim:
        return "sdf_hidden", (f"must exceed model.sdf_features + {dim} "
                              f"({s.sdf_features + dim}: the decoder's skip connection), got {s.sdf_hidden}")
    return None


def _model_section(values: dict, path: Path, overrides=()) -> ModelSettings:
    """``[model]`` values -> ModelSettings; a bad value is a DataError naming the file (or the override) and
    ``model.<key>``."""
    model = section(ModelSettings, values, path, "model", overrides)
    problem = model_problem(model)
    if problem:
        raise DataError(path, f"model.{problem[0]}", problem[1])
    return model


# upstream's optimisation (main/train.py, main/config.py, common/base.py of amathislab/HOISDF @666e5b7)
_UPSTREAM_OPTIMISER = {"optimizer": "adamw", "weight_decay": 0.01, "lr": 1e-4, "lr_drop": 9, "lr_gamma": 0.7,
                       "epochs": 70, "batch_size": 22, "point_sampling_epoch": 40}
RECIPES: dict[str, dict[str, dict]] = {
    # upstream's training as its released code runs it; every key is checked against that code in
    # docs/training.md ("Training as the authors did", with file:line). Keys other work adds go in their section.
    "upstream": {
        "model": {"normalize_input": False,  # raw [0, 1] input: ToTensor()/255 (data/dexycb.py:622)
                  "density_sign": "code",  # sigmoid(+d/beta)/beta (main/model.py:125)
                  "pixel_convention": "upstream",  # grid_sample(align_corners=True) (main/model.py:152-171)
                  "sheared_grid": True,  # the sheared 64^3 lattice (main/model.py:260-273)
                  "object_rotation": "axis_angle",  # mean of the per-point axis-angles (validation only)
                  # pinned at upstream's values, today also the defaults (main/config.py)
                  "image_size": 256, "hand_queries": 600, "object_queries": 200, "grid_resolution": 64,
                  "dropout": 0.1,
                  "sdf_dropout": 0.2, "freeze_bn_affine": True, "sampling": "absolute",
                  "feature_augmentation": "density", "cross_field": "sdf", "test_boxes": "gt", "fixed_shape": False,
                  "sdf_scale": 3.1, "sdf_clamp": 0.15, "beta_init": 0.1, "beta_min": 2e-3, "cls_dist": 0.04,
                  "rot6d": "raw",  # the pose head's raw 6D code, no identity offset (common/nets/mano_head.py)
                  "beta_floor": "project",  # the density width projected in place (main/model.py)
                  "field_density": "ranking"},  # tokens reuse the ranking pass's SDFs, dropout mask included
        "train": {**_UPSTREAM_OPTIMISER, "lr_min": 1e-5, "field_prob": 0.6, "noise_ratios": (0.3, 0.7),
                  "noise_dists": (0.03, 0.05, 0.07), "near": 0.05, "epoch_samples": 0,
                  "bf16": False,  # fp32 throughout (main/train.py: no autocast)
                  "shuffle": "global",  # DataLoader(shuffle=True, drop_last=True) (common/base.py:79-86)
                  "val_schedule": "upstream",  # every 5 epochs before point_sampling_epoch, then every epoch
                  "val_batches": 0},  # the whole validation store (main/train.py:164-169, 202)
        # upstream's per-sample warp, blur and colour jitter from record.upstream_region stores (data/dexycb.py,
        # data/ho3d.py, data/dataset_util.py); the heatmap target summed on uv / 256 * 128 (main/model.py)
        "augment": {"upstream": True, "heatmap_target": "upstream"},
        "loss": {"sdf_hand": 50.0, "sdf_obj": 25.0, "heatmap": 1e-3, "hand_seg": 1.0, "obj_seg": 1.0, "joint_vote": 0.1,
                 "joint_cls": 1.0, "joint_all": 0.1, "mano_verts": 1e4, "mano_joints": 1e4, "mano_pose": 10.0,
                 "mano_shape": 0.1, "shape_reg": 1e-6, "obj_rot": 0.7, "obj_trans": 100.0,  # main/config.py:136-151
                 "left_hands": "right_layer",  # right MANO layer, left betas (common/nets/mano_head.py:257-266)
                 "synthetic_betas": "zeros"},  # rendered frames' MANO targets are zeros (data/ho3d.py:249)
    },
    # upstream's optimisation with this project's own model, precision and data defaults (the dataclass defaults
    # below): what "released" set before the upstream recipe existed; the toy and the bare defaults use it
    "project": {"train": dict(_UPSTREAM_OPTIMISER)},
    # the paper's text ("Implementation and Training Details"): Adam, mini-batch 32, lr 1e-4 x0.7 every 5 epochs,
    # "about 40 epochs"; it gives no weight decay (Adam's default 0) and no field-sampling epoch: 23 keeps
    # upstream's 40/70 ratio (our choice); the project's model defaults
    "paper_text": {"train": {"optimizer": "adam", "weight_decay": 0.0, "lr": 1e-4, "lr_drop": 5, "lr_gamma": 0.7,
                             "epochs": 40, "batch_size": 32, "point_sampling_epoch": 23}},
}
"""``train.recipe`` presets, per section: their values fill every key the TOML and the overrides leave unset
(explicit TOML or override > recipe > the dataclass defaults)."""
RENAMED_RECIPES = {"released": "project"}  # old name -> new name (checkpoints and run folders store the old one)
OPTIMIZERS = ("adamw", "adam")
VAL_SCHEDULES = ("every", "upstream")  # train.val_schedule (hoisdf.training.trainer.validates_after)


@dataclass(frozen=True)
class TrainSettings:
    """Training settings; the defaults are the ``project`` recipe: upstream's optimisation (``RECIPES``)."""

    recipe: str = "project"  # upstream | project | paper_text: the preset the unset keys of every section come from
    optimizer: str = "adamw"  # adamw | adam
    epochs: int = 70  # epochs of the run (one epoch: epoch_samples or the stores' sizes times their weights)
    batch_size: int = 22  # per process (upstream: per GPU)
    lr: float = 1e-4  # peak learning rate
    weight_decay: float = 0.01  # decoupled weight decay (AdamW)
    lr_drop: int = 9  # epochs per step of the StepLR schedule
    lr_gamma: float = 0.7  # learning-rate factor at every lr_drop epochs
    lr_min: float = 1e-5  # learning-rate floor of the schedule
    point_sampling_epoch: int = 40  # from this epoch on, field-guided sampling with probability field_prob
    field_prob: float = 0.6  # probability of a field-guided training step once point_sampling_epoch is reached
    noise_ratios: tuple[float, ...] = (0.3, 0.7)  # epoch progress where the noise steps up
    noise_dists: tuple[float, ...] = (0.03, 0.05, 0.07)  # scaled units: query-point noise half-widths
    near: float = 0.05  # m: |sdf| below which SDF rows are "near" (training query points)
    sdf_rows_hand: int = 0  # SDF rows the loader draws per sample for the hand (0: model.hand_queries, see sdf_rows)
    sdf_rows_object: int = 0  # the same for the object (0: model.object_queries)
    epoch_samples: int = 0  # 0: the stores' sizes times their weights
    workers: int = 4  # loader worker processes per rank
    seed: int = 0  # seed of initialisation, data order, SDF row draws and augmentation
    bf16: bool = True  # autocast on CUDA (geometry stays fp32: hoisdf.model.precision)
    log_every: int = 20  # steps between TensorBoard scalars
    val_every: int = 1  # epochs between validations (0: never; val_schedule = "every")
    val_schedule: str = "every"  # every: each val_every epochs | upstream: every 5 epochs, each from point_sampling_epoch
    val_batches: int = 50  # batches of each validation pass (0: the whole validation stores)
    ckpt_every: int = 1  # epochs between checkpoints
    max_steps: int = 0  # stop after this many steps in total (0: run all epochs)
    shuffle: str = "stream"  # stream: shards + shuffle_buffer | global: one permutation of all records (docs/training.md)
    shuffle_buffer: int = 64  # stream: records in each worker's shuffle buffer (beside the per-epoch shard reshuffle)
    record_keys: bool = False  # write the record keys each rank trained on (for checking DDP splits)
    CHOICES: ClassVar[dict] = {"recipe": tuple(RECIPES), "optimizer": OPTIMIZERS, "shuffle": SHUFFLES,
                               "val_schedule": VAL_SCHEDULES}
    LIMITS: ClassVar[dict] = {
        "epochs": (">= 1",), "batch_size": (">= 1",), "lr": ("> 0",), "weight_decay": (">= 0",), "lr_drop": (">= 1",),
        "lr_gamma": ("> 0",), "lr_min": (">= 0",), "point_sampling_epoch": (">= 0",), "field_prob": (">= 0", "<= 1"),
        "noise_ratios": (">= 0", "<= 1"), "noise_dists": (">= 0",), "near": ("> 0",),
        "epoch_samples": (">= 0",),  # 0: the stores' sizes times their weights
        "sdf_rows_hand": (">= 0",), "sdf_rows_object": (">= 0",),  # 0: the model's query counts
        "workers": (">= 0",),  # 0: load in the training process
        "seed": (">= 0",), "log_every": (">= 1",), "val_every": (">= 0",), "val_batches": (">= 0",),
        "ckpt_every": (">= 0",), "max_steps": (">= 0",), "shuffle_buffer": (">= 0",)}


@dataclass(frozen=True)
class LossWeights:
    """``[loss]``: the weight of each term of :class:`hoisdf.training.losses.HOISDFLoss`, and two target choices."""

    sdf_hand: float = 50.0  # L1 of clamped hand SDF values (scaled units)
    sdf_obj: float = 25.0  # L1 of clamped object SDF values (scaled units)
    heatmap: float = 1e-3  # on a 0..255 heatmap, as the reference
    hand_seg: float = 1.0  # BCE of the hand mask logits
    obj_seg: float = 1.0  # BCE of the object mask logits
    joint_vote: float = 0.1  # per-point votes (mm, SmoothL1) of the points within cls_dist of a joint
    joint_cls: float = 1.0  # BCE of which joint's neighbourhood (cls_dist) a hand query point lies in
    joint_all: float = 0.1  # softmax-aggregated joints (mm, SmoothL1)
    mano_verts: float = 1e4  # MSE, metres
    mano_joints: float = 1e4  # MSE of the MANO joints, metres
    mano_pose: float = 10.0  # MSE of the 16 rotation matrices
    mano_shape: float = 0.1  # MSE of the MANO betas
    shape_reg: float = 1e-6  # IK variant: betas towards 0
    obj_rot: float = 0.7  # SmoothL1 of per-point axis-angles
    obj_trans: float = 100.0  # SmoothL1 of per-point translations, metres
    left_hands: str = "mirrored"  # MANO targets of mirrored (left) hands: mirrored layer | right_layer (upstream)
    synthetic_betas: str = "record"  # MANO shape target of synthetic records: record | zeros (upstream's renders)
    TERMS: ClassVar[tuple] = ("sdf_hand", "sdf_obj", "heatmap", "hand_seg", "obj_seg", "joint_vote", "joint_cls",
                              "joint_all", "mano_verts", "mano_joints", "mano_pose", "mano_shape", "shape_reg",
                              "obj_rot", "obj_trans")  # the weighted terms (the fields above the two choices)
    LIMITS: ClassVar[dict] = {name: (">= 0",) for name in TERMS}
    CHOICES: ClassVar[dict] = {"left_hands": ("mirrored", "right_layer"), "synthetic_betas": ("record", "zeros")}


@dataclass(frozen=True)
class TrainConfig:
    model: ModelSettings = field(default_factory=ModelSettings)
    train: TrainSettings = field(default_factory=TrainSettings)
    augment: AugmentSettings = field(default_factory=AugmentSettings)
    loss: LossWeights = field(default_factory=LossWeights)

    def as_dict(self) -> dict:
        return asdict(self)


TRAIN_SECTIONS = section_names(TrainConfig)  # ("model", "train", "augment", "loss"): what training reads of a file
SECTION_SETTINGS = {"model": ModelSettings, "train": TrainSettings, "augment": AugmentSettings, "loss": LossWeights}
# The build's sections of the same files (hoidata.records.settings.BUILD_SECTIONS, which training does not import:
# it stands beside the build, not on it; tests/test_settings_floor.py holds the two equal)
BUILD_SECTIONS = ("dataset", "record", "store")
BUILD_READER = {name: "hoidata build-sdf" for name in BUILD_SECTIONS}  # section -> the command that reads it


def refuse_build_overrides(overrides: list[str], path: Path) -> None:
    """An override of a section training does not read is a DataError naming ``path`` and the key."""
    refuse_unused(list(overrides), TRAIN_SECTIONS, "training", path, BUILD_READER)


def load_train_config(name_or_path: str | None, overrides: list[str] = ()) -> TrainConfig:
    """Pipeline TOML (or the defaults when None) + ``section.key=value`` overrides -> TrainConfig.

    ``train.recipe`` (default "project") fills the keys of every section left unset from :data:`RECIPES`.
    ``augment.input_size`` follows ``model.image_size`` unless set; a mismatch is an error.
    """
    return resolve_train_config(name_or_path, overrides)[0]


def resolve_train_config(name_or_path: str | None, overrides: list[str] = ()) -> tuple[TrainConfig, dict[str, str]]:
    """:func:`load_train_config` and where each key that is not its dataclass default came from:
    ``{"section.key": "command line" | the file | "recipe NAME"}`` (precedence in that order)."""
    where = resolve_pipeline(name_or_path) if name_or_path else Path("<defaults>")
    refuse_build_overrides(overrides, where)
    if name_or_path:
        path, data = read_pipeline(name_or_path, overrides)
        file_data = read_pipeline(name_or_path)[1]
    else:
        path, file_data = where, {}
        data = apply_overrides({}, overrides, path)
    check_sections(data, path, TRAIN_SECTIONS, BUILD_SECTIONS)  # training knows every reader of the file
    name = data.get("train", {}).get("recipe", TrainSettings.recipe)
    recipe = recipe_sections(name, origin(path, overrides, "train.recipe"))
    merged = {s: {**recipe.get(s, {}), **data.get(s, {})} for s in TRAIN_SECTIONS}
    model = _model_section(merged["model"], path, overrides)
    train = section(TrainSettings, merged["train"], path, "train", overrides)
    check_choices(train, path, "train")
    merged["augment"].setdefault("input_size", model.image_size)
    augment = section(AugmentSettings, merged["augment"], path, "augment", overrides)
    if augment.input_size != model.image_size:
        raise DataError(path, "augment.input_size", f"must equal model.image_size ({model.image_size})")
    loss = section(LossWeights, merged["loss"], path, "loss", overrides)
    check_choices(loss, path, "loss")
    given = {item.partition("=")[0].strip() for item in overrides}
    label = str(path) if Path(str(name_or_path)).suffix == ".toml" else f"pipelines/{path.name}"
    sources = {}
    for s in TRAIN_SECTIONS:
        for key in merged[s]:
            sources[f"{s}.{key}"] = ("command line" if f"{s}.{key}" in given else label
                                     if key in file_data.get(s, {}) else f"recipe {name}" if key in recipe.get(s, {})
                                     else "derived")  # augment.input_size from model.image_size
    config = TrainConfig(model, replace(train, noise_ratios=tuple(train.noise_ratios),
                                        noise_dists=tuple(train.noise_dists)), augment, loss)
    check_sdf_rows(config, path, overrides)
    return config, sources


def sdf_rows(config: TrainConfig) -> tuple[int, int]:
    """SDF rows the loader draws per training sample (hand, object): ``train.sdf_rows_*``, or where 0 the model's
    query counts, as upstream (the GT-guided query points are the first rows drawn; docs/settings.md)."""
    t, m = config.train, config.model
    return t.sdf_rows_hand or m.hand_queries, t.sdf_rows_object or m.object_queries


def check_sdf_rows(config: TrainConfig, path, overrides=()) -> None:
    """``train.sdf_rows_*`` is 0 or at least the model's query count, else a DataError naming the key."""
    for who, queries in (("hand", "hand_queries"), ("object", "object_queries")):
        rows, need = getattr(config.train, f"sdf_rows_{who}"), getattr(config.model, queries)
        if 0 < rows < need:
            raise DataError(origin(path, overrides, f"train.sdf_rows_{who}", f"model.{queries}"),
                            f"train.sdf_rows_{who}", f"must be 0 (model.{queries}) or at least model.{queries} "
                            f"({need}): the training query points are the first rows drawn, got {rows}")


def recipe_sections(name, where) -> dict[str, dict]:
    """The sections :data:`RECIPES` sets for ``name``; an unknown or renamed recipe is a DataError naming ``where``
    (the file, and the command line's override of ``train.recipe`` when there is one) and ``train.recipe``."""
    if name in RENAMED_RECIPES:
        raise DataError(where, "train.recipe", (
            f"{name!r} is now {RENAMED_RECIPES[name]!r} (upstream's optimiser with this project's model and precision "
            f"defaults, what {name!r} set); 'upstream' trains as upstream's code (docs/training.md)"))
    if name not in RECIPES:
        raise DataError(where, "train.recipe", f"unknown recipe {name!r}; expected one of {sorted(RECIPES)}")
    return RECIPES[name]


def check_choices(settings, path: Path, name: str) -> None:
    """Every key of ``settings`` named in its class's ``CHOICES`` holds one of them, else a DataError naming
    ``path`` and ``name.key``."""
    for key, allowed in getattr(settings, "CHOICES", {}).items():
        if getattr(settings, key) not in allowed:
            raise DataError(path, f"{name}.{key}", f"unknown {key} {getattr(settings, key)!r}; expected one of {allowed}")


def config_from_dict(data: dict, path: Path | str = "<checkpoint>") -> TrainConfig:
    """Inverse of :meth:`TrainConfig.as_dict` (checkpoints store the resolved config as a dict); errors name
    ``path`` (the checkpoint file). The values are resolved, so no recipe is applied; a renamed recipe's old name
    (``released``, in checkpoints written before ``upstream`` existed) reads as its new one."""
    path = Path(path)
    if not isinstance(data, dict) or not all(isinstance(data.get(k, {}), dict) for k in SECTION_SETTINGS):
        raise DataError(path, "config", "expected a dict of settings sections")
    data = {name: current_names(data.get(name, {}), getattr(cls, "RENAMED", {}))  # copies: the stored dict is kept
            for name, cls in SECTION_SETTINGS.items()}
    model = _model_section(data["model"], path)
    train_values = data["train"]
    if train_values.get("recipe") in RENAMED_RECIPES:
        train_values["recipe"] = RENAMED_RECIPES[train_values["recipe"]]
    train = section(TrainSettings, train_values, path, "train")
    check_choices(train, path, "train")
    loss = section(LossWeights, data["loss"], path, "loss")
    check_choices(loss, path, "loss")
    config = TrainConfig(model, train, section(AugmentSettings, data["augment"], path, "augment"), loss)
    check_sdf_rows(config, path)
    return config


def overridden_config(data: dict, overrides: list[str], path: Path | str) -> TrainConfig:
    """A saved config (:meth:`TrainConfig.as_dict`, as a checkpoint holds it) with ``section.key=value``
    ``overrides`` applied (``data`` is left as it is); errors name ``path`` (the checkpoint or run file), also an
    override of a section training does not read."""
    import copy

    refuse_build_overrides(list(overrides), Path(path))
    given = apply_overrides({}, list(overrides), Path(path))
    for name, cls in SECTION_SETTINGS.items():
        refuse_renamed(cls, given.get(name, {}), Path(path), name, list(overrides))
    if any(item.partition("=")[0].strip() == "train.recipe" for item in overrides):
        raise DataError(path, "train.recipe", "a recipe fills a run's settings when it starts; a saved run holds "
                                              "them resolved: override the keys themselves")
    return config_from_dict(apply_overrides(copy.deepcopy(data), list(overrides), Path(path)), path)


def describe_config(config: TrainConfig, sources: dict[str, str]) -> list[str]:
    """Lines for the start of a run: the recipe, then every key not at its dataclass default by where it came from
    (the recipe, the file, the command line); a recipe key that the file or the command line replaced shows the
    recipe's value beside it."""
    recipe = RECIPES.get(config.train.recipe, {})
    values = config.as_dict()
    lines = [f'train.recipe = "{config.train.recipe}"; settings not listed are hoisdf/config.py defaults']
    width = max((len(s) for s in sources.values()), default=0)
    for key, source in sources.items():
        section_name, name = key.split(".", 1)
        value = values[section_name][name]
        note = ""
        if name in recipe.get(section_name, {}) and not source.startswith("recipe"):
            note = f"  (recipe {config.train.recipe}: {toml_value(recipe[section_name][name])})"
        lines.append(f"  {source:<{width}}  {key} = {toml_value(value)}{note}")
    return lines
