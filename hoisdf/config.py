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
    read_pipeline,
    refuse_unused,
    resolve_pipeline,
    section,
    section_names,
)
from hoisdf.data.augment import AugmentSettings
from hoisdf.data.loader import SHUFFLES
from hoisdf.model.encoding import PIXEL_CONVENTIONS
from hoisdf.training.losses import LossWeights


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
    n_hand: int = 600  # query points of the hand field passed to the pose stage
    n_object: int = 200  # query points of the object field passed to the pose stage
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
                                  "sdf_features", "sdf_hidden", "token_hidden", "n_hand", "n_object", "chunk")},
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
        "pixel_convention": PIXEL_CONVENTIONS,
        "rot6d": ("offset", "raw"),
        "beta_floor": ("clamp", "project"),
        "field_density": ("fresh", "ranking")}
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


def _model_section(values: dict, path: Path) -> ModelSettings:
    """``[model]`` values -> ModelSettings; a bad value is a DataError naming the file and ``model.<key>``."""
    model = section(ModelSettings, values, path, "model")
    problem = model_problem(model)
    if problem:
        raise DataError(path, f"model.{problem[0]}", problem[1])
    return model


RECIPES: dict[str, dict] = {
    # upstream's released code (main/train.py, main/config.py of amathislab/HOISDF): what its checkpoints used
    "released": {"optimizer": "adamw", "weight_decay": 0.01, "lr": 1e-4, "lr_drop": 9, "lr_gamma": 0.7,
                 "epochs": 70, "batch_size": 22, "point_sampling_epoch": 40},
    # the paper's text ("Implementation and Training Details"): Adam, mini-batch 32, lr 1e-4 x0.7 every 5 epochs,
    # "about 40 epochs"; it gives no weight decay (Adam's default 0) and no field-sampling epoch: 23 keeps
    # upstream's 40/70 ratio (our choice)
    "paper_text": {"optimizer": "adam", "weight_decay": 0.0, "lr": 1e-4, "lr_drop": 5, "lr_gamma": 0.7,
                   "epochs": 40, "batch_size": 32, "point_sampling_epoch": 23},
}
"""``train.recipe`` presets: their values fill every ``[train]`` key the TOML and the overrides leave unset."""
OPTIMIZERS = ("adamw", "adam")


@dataclass(frozen=True)
class TrainSettings:
    """Training settings; the defaults are upstream's released recipe (``RECIPES["released"]``)."""

    recipe: str = "released"  # released | paper_text: the preset the unset keys below come from
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
    epoch_samples: int = 0  # 0: the stores' sizes times their weights
    workers: int = 4  # loader worker processes per rank
    seed: int = 0  # seed of initialisation, data order, SDF row draws and augmentation
    bf16: bool = True  # autocast on CUDA (geometry stays fp32: hoisdf.model.precision)
    log_every: int = 20  # steps between TensorBoard scalars
    val_every: int = 1  # epochs between validations (0: never)
    val_batches: int = 50  # batches of each validation pass
    ckpt_every: int = 1  # epochs between checkpoints
    max_steps: int = 0  # stop after this many steps in total (0: run all epochs)
    shuffle: str = "stream"  # stream: shards + shuffle_buffer | global: one permutation of all records (docs/training.md)
    shuffle_buffer: int = 64  # stream: records in each worker's shuffle buffer (beside the per-epoch shard reshuffle)
    record_keys: bool = False  # write the record keys each rank trained on (for checking DDP splits)
    LIMITS: ClassVar[dict] = {
        "epochs": (">= 1",), "batch_size": (">= 1",), "lr": ("> 0",), "weight_decay": (">= 0",), "lr_drop": (">= 1",),
        "lr_gamma": ("> 0",), "lr_min": (">= 0",), "point_sampling_epoch": (">= 0",), "field_prob": (">= 0", "<= 1"),
        "noise_ratios": (">= 0", "<= 1"), "noise_dists": (">= 0",), "near": ("> 0",),
        "epoch_samples": (">= 0",),  # 0: the stores' sizes times their weights
        "workers": (">= 0",),  # 0: load in the training process
        "seed": (">= 0",), "log_every": (">= 1",), "val_every": (">= 0",), "val_batches": (">= 1",),
        "ckpt_every": (">= 0",), "max_steps": (">= 0",), "shuffle_buffer": (">= 0",)}


@dataclass(frozen=True)
class TrainConfig:
    model: ModelSettings = field(default_factory=ModelSettings)
    train: TrainSettings = field(default_factory=TrainSettings)
    augment: AugmentSettings = field(default_factory=AugmentSettings)
    loss: LossWeights = field(default_factory=LossWeights)

    def as_dict(self) -> dict:
        return asdict(self)


TRAIN_SECTIONS = section_names(TrainConfig)  # ("model", "train", "augment", "loss"): what training reads of a file
# The build's sections of the same files (hoidata.pipeline.settings.BUILD_SECTIONS, which training does not import:
# it stands beside the build, not on it; tests/test_settings_floor.py holds the two equal)
BUILD_SECTIONS = ("dataset", "record", "store")
BUILD_READER = {name: "hoidata build-sdf" for name in BUILD_SECTIONS}  # section -> the command that reads it


def refuse_build_overrides(overrides: list[str], path: Path) -> None:
    """An override of a section training does not read is a DataError naming ``path`` and the key."""
    refuse_unused(list(overrides), TRAIN_SECTIONS, "training", path, BUILD_READER)


def load_train_config(name_or_path: str | None, overrides: list[str] = ()) -> TrainConfig:
    """Pipeline TOML (or the defaults when None) + ``section.key=value`` overrides -> TrainConfig.

    ``train.recipe`` (default "released") fills the ``[train]`` keys left unset from :data:`RECIPES`.
    ``augment.input_size`` follows ``model.image_size`` unless set; a mismatch is an error.
    """
    where = resolve_pipeline(name_or_path) if name_or_path else Path("<defaults>")
    refuse_build_overrides(overrides, where)
    if name_or_path:
        path, data = read_pipeline(name_or_path, overrides)
    else:
        path = where
        data = apply_overrides({}, overrides, path)
    check_sections(data, path, TRAIN_SECTIONS, BUILD_SECTIONS)  # training knows every reader of the file
    model = _model_section(data.get("model", {}), path)
    train = section(TrainSettings, with_recipe(data.get("train", {}), path), path, "train")
    augment_values = dict(data.get("augment", {}))
    augment_values.setdefault("input_size", model.image_size)
    augment = section(AugmentSettings, augment_values, path, "augment")
    if augment.input_size != model.image_size:
        raise DataError(path, "augment.input_size", f"must equal model.image_size ({model.image_size})")
    loss = section(LossWeights, data.get("loss", {}), path, "loss")
    return TrainConfig(model, replace(train, noise_ratios=tuple(train.noise_ratios),
                                      noise_dists=tuple(train.noise_dists)), augment, loss)


def with_recipe(values: dict, path: Path) -> dict:
    """``[train]`` values over their recipe's preset; an unknown recipe or optimizer is a DataError."""
    recipe = values.get("recipe", "released")
    if recipe not in RECIPES:
        raise DataError(path, "train.recipe", f"unknown recipe {recipe!r}; expected one of {sorted(RECIPES)}")
    merged = {**RECIPES[recipe], **values}
    check_shuffle(merged.get("shuffle", "stream"), path)
    if merged["optimizer"] not in OPTIMIZERS:
        raise DataError(path, "train.optimizer",
                        f"unknown optimizer {merged['optimizer']!r}; expected one of {OPTIMIZERS}")
    return merged


def check_shuffle(value, path: Path) -> None:
    """``train.shuffle`` is one of SHUFFLES, else a DataError naming ``path`` and the key."""
    if value not in SHUFFLES:
        raise DataError(path, "train.shuffle", f"unknown shuffle {value!r}; expected one of {SHUFFLES}")


def config_from_dict(data: dict, path: Path | str = "<checkpoint>") -> TrainConfig:
    """Inverse of :meth:`TrainConfig.as_dict` (checkpoints store the resolved config as a dict); errors name
    ``path`` (the checkpoint file)."""
    path = Path(path)
    if not isinstance(data, dict) or not all(isinstance(data.get(k, {}), dict) for k in ("model", "train", "augment", "loss")):
        raise DataError(path, "config", "expected a dict of settings sections")
    model = _model_section(data.get("model", {}), path)
    train = section(TrainSettings, data.get("train", {}), path, "train")
    check_shuffle(train.shuffle, path)
    return TrainConfig(model, train, section(AugmentSettings, data.get("augment", {}), path, "augment"),
                       section(LossWeights, data.get("loss", {}), path, "loss"))


def overridden_config(data: dict, overrides: list[str], path: Path | str) -> TrainConfig:
    """A saved config (:meth:`TrainConfig.as_dict`, as a checkpoint holds it) with ``section.key=value``
    ``overrides`` applied (``data`` is left as it is); errors name ``path`` (the checkpoint or run file), also an
    override of a section training does not read."""
    import copy

    refuse_build_overrides(list(overrides), Path(path))
    return config_from_dict(apply_overrides(copy.deepcopy(data), list(overrides), Path(path)), path)
