"""hoisdf.model.build: the model composed of parts, every setting string read once in build_model.

The numbers of the composed model are guarded by tests/test_import_upstream.py (upstream's golden outputs) and the
other model tests; these tests hold the structure."""

from __future__ import annotations

import ast
import inspect
import textwrap
from dataclasses import replace

import pytest
import torch

from hoisdf.config import ModelSettings, load_train_config
from hoisdf.model import build as B
from hoisdf.model.backbone import DECODERS
from hoisdf.model.encoding import PIXEL_CONVENTIONS
from hoisdf.model.hoisdf import HOISDF, STATE_RENAMES, renamed_state
from hoisdf.model.regressors import REGRESSORS

TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=1",
        "model.decoder_layers=1", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=16"]


def _is_str(node) -> bool:
    return isinstance(node, ast.Constant) and isinstance(node.value, str)


def _string_compares(fn) -> list[str]:
    """Setting switches in ``fn``'s source (a function, or a file's text): ``x == "a"`` / ``!=``, and
    ``x in ("a", "b")`` against a literal (``"key" in batch``, a look-up of a data key, is not one)."""
    found = []
    source = fn if isinstance(fn, str) else textwrap.dedent(inspect.getsource(fn))
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Compare):
            continue
        operands = [node.left, *node.comparators]
        equal = any(isinstance(op, (ast.Eq, ast.NotEq)) for op in node.ops) and any(map(_is_str, operands))
        member = any(isinstance(c, (ast.Tuple, ast.List, ast.Set)) and any(map(_is_str, c.elts))
                     for c in node.comparators)
        if equal or member:
            found.append(ast.unparse(node))
    return found


def test_no_file_of_the_model_compares_a_setting_string():
    """Every setting string is looked up in a table of ``hoisdf/model/build.py`` (or the module that owns the
    choice) once; the parts hold the chosen objects and compare no string (issue 34)."""
    from pathlib import Path

    files = sorted((Path(B.__file__).parent).glob("*.py"))
    assert len(files) >= 14 and any(f.name == "hoisdf.py" for f in files)
    found = {f.name: _string_compares(f.read_text()) for f in files}
    assert not any(found.values()), {k: v for k, v in found.items() if v}
    # the finder finds switches where there are some
    assert _string_compares('if s.sampling == "gradient":\n    pass\n') == ["s.sampling == 'gradient'"]
    assert _string_compares('ok = mode in ("a", "b")\n') == ["mode in ('a', 'b')"]
    assert _string_compares(_is_str) == [] and _string_compares('ok = "hand_points" in batch\n') == []


def test_the_settings_choices_are_exactly_the_builders_parts():
    tables = {"sampling": B.TRAINING_ROWS, "cross_field": B.CROSS_FIELDS, "pose_regressor": REGRESSORS,
              "density_sign": B.DENSITY_SIGNS, "object_rotation": B.OBJECT_ROTATIONS, "test_boxes": B.BOXES,
              "field_density": B.REUSE_RANKING_SDF}
    for key, table in tables.items():
        assert set(ModelSettings.CHOICES[key]) == set(table), key
    assert set(B.RANKINGS) == set(B.TRAINING_ROWS)
    assert set(DECODERS) == {"small", "big"}
    assert set(ModelSettings.CHOICES["pixel_convention"]) == set(PIXEL_CONVENTIONS)
    for value in ModelSettings.CHOICES["feature_augmentation"]:
        assert B.token_features(ModelSettings(feature_augmentation=value)) is not None


@pytest.mark.parametrize("key", sorted(ModelSettings.CHOICES))
def test_a_bad_choice_is_one_line_naming_the_key(key):
    with pytest.raises(ValueError, match=f"model.{key}") as info:  # through the settings (a DataError)
        load_train_config(None, TINY + [f'model.{key}="nope"'])
    assert "\n" not in str(info.value) and "nope" in str(info.value)
    settings = replace(load_train_config(None, TINY).model, **{key: "nope"})
    with pytest.raises(ValueError, match=f"model.{key} must be one of"):  # settings built in code
        B.build_model(settings, None)


def test_the_model_is_a_few_keyword_parts_and_each_regressor_owns_its_heads():
    params = inspect.signature(HOISDF.__init__).parameters
    assert len(params) - 1 <= 8 and all(p.kind is p.KEYWORD_ONLY for name, p in params.items() if name != "self")
    heads = {"mano": {"hand_decoder", "mano_head", "vote_head"}, "mano_only": {"hand_decoder", "mano_head"},
             "voting": {"vote_head"}, "ik": {"hand_decoder", "shape_head", "vote_head"}}
    for name, cls in REGRESSORS.items():
        model = B.build_model(load_train_config(None, TINY + [f'model.pose_regressor="{name}"']).model, None)
        keys = list(model.state_dict())
        assert {k.split(".")[0] for k in keys} == {"widths", "backbone", "features", "fields", "pose"}
        assert {k.split(".")[2] for k in keys if k.startswith("pose.regressor.")} == heads[name]
        assert {n for n, _ in cls(8, 1, 2, 16, 0.0).named_children()} == heads[name]


def test_a_flat_state_dict_loads_into_the_grouped_model():
    """Run folders written before the stages (``hand_sdf.*``, ``mano_head.*``, ...) load: their keys are renamed
    where checkpoints load, and their parameter order (their optimizer state) is the grouped model's."""
    from hoisdf.training.checkpoint import load_weights

    model = B.build_model(load_train_config(None, TINY).model, None)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    inverse = {new: old for old, new in STATE_RENAMES.items()}

    def flat(key):
        for new, old in inverse.items():
            if key == new or (new.endswith(".") and key.startswith(new)):
                return old + key[len(new):]
        return key

    old = {flat(k): v + 1 for k, v in state.items()}
    assert {k.split(".")[0] for k in old} >= {"sdf_in", "hand_sdf", "hand_beta", "mano_head", "obj_head"}
    assert list(renamed_state(old)) == list(state) and renamed_state(state).keys() == state.keys()
    load_weights(model, old, "old.pt")
    assert all(torch.equal(model.state_dict()[k], v + 1) for k, v in state.items())
    order = []  # the flat model registered its modules in this order: the optimizer state's parameter order
    for name, _ in model.named_parameters():
        top = flat(name).split(".")[0]
        order += [] if order and order[-1] == top else [top]
    assert order == ["hand_beta", "obj_beta", "backbone", "sdf_in", "token_in", "hand_sdf", "obj_sdf", "hand_encoder",
                     "obj_encoder", "hand_decoder", "mano_head", "vote_head", "obj_head"]


def test_rotations_are_written_once():
    """Rodrigues and the other conversions live in hoidata.geometry.rotation only (both packages import it)."""
    from pathlib import Path

    names = {"axis_angle_to_matrix", "batch_rodrigues", "rodrigues", "skew", "_skew", "rot6d_to_matrix",
             "matrix_to_axis_angle", "matrix_to_quaternion", "quaternion_to_matrix", "quaternion_to_axis_angle"}
    root = Path(__file__).resolve().parents[1]
    found = {}
    for path in [*root.glob("hoidata/**/*.py"), *root.glob("hoisdf/**/*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef) and node.name in names:
                found.setdefault(node.name, []).append(str(path.relative_to(root)))
    assert set(found) >= names - {"batch_rodrigues", "rodrigues", "_skew"}
    assert all(files == ["hoidata/geometry/rotation.py"] for files in found.values()), found


def test_a_run_folder_from_before_the_parts_loads_with_its_settings(tmp_path):
    """A checkpoint as the flat model wrote it (flat keys, ``model.n_hand`` / ``n_object`` in its config) loads
    through :func:`hoisdf.training.checkpoint.load_model`, weights and settings as they were."""
    from hoisdf.config import TrainConfig
    from hoisdf.training.checkpoint import load_model, save_checkpoint

    config = load_train_config(None, TINY)
    torch.manual_seed(5)
    model = B.build_model(config.model, None)
    inverse = {new: old for old, new in STATE_RENAMES.items()}
    flat = {}
    for key, value in model.state_dict().items():
        new = next((n for n in inverse if key == n or (n.endswith(".") and key.startswith(n))), None)
        flat[key if new is None else inverse[new] + key[len(new):]] = value
    stored = config.as_dict()
    stored["model"]["n_hand"], stored["model"]["n_object"] = stored["model"].pop("hand_queries"), stored["model"].pop(
        "object_queries")
    save_checkpoint(tmp_path / "checkpoints" / "last.pt", {"model": flat, "config": stored})
    loaded, loaded_config = load_model(tmp_path, None)
    assert isinstance(loaded_config, TrainConfig) and loaded_config.model == config.model
    assert all(torch.equal(loaded.state_dict()[k], v) for k, v in model.state_dict().items())
