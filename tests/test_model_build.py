"""hoisdf.model.build: the model composed of parts, every setting string read once in build_model.

The numbers of the composed model are guarded by tests/test_import_upstream.py (upstream's golden outputs) and the
other model tests; these tests hold the structure."""

from __future__ import annotations

import ast
import inspect
import textwrap
from dataclasses import replace

import pytest

from hoisdf.config import ModelSettings, load_train_config
from hoisdf.model import build as B
from hoisdf.model.encoding import PIXEL_CONVENTIONS
from hoisdf.model.heads import mean_rotation
from hoisdf.model.hoisdf import HOISDF
from hoisdf.model.regressors import REGRESSORS

TINY = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=1",
        "model.decoder_layers=1", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
        "model.token_hidden=[48]", "model.n_hand=32", "model.n_object=16", "model.grid_resolution=16"]


def _is_str(node) -> bool:
    return isinstance(node, ast.Constant) and isinstance(node.value, str)


def _string_compares(fn) -> list[str]:
    """Setting switches in ``fn``'s source: ``x == "a"`` / ``!=``, and ``x in ("a", "b")`` against a literal
    (``"key" in batch``, a look-up of a data key, is not one)."""
    found = []
    for node in ast.walk(ast.parse(textwrap.dedent(inspect.getsource(fn)))):
        if not isinstance(node, ast.Compare):
            continue
        operands = [node.left, *node.comparators]
        equal = any(isinstance(op, (ast.Eq, ast.NotEq)) for op in node.ops) and any(map(_is_str, operands))
        member = any(isinstance(c, (ast.Tuple, ast.List, ast.Set)) and any(map(_is_str, c.elts))
                     for c in node.comparators)
        if equal or member:
            found.append(ast.unparse(node))
    return found


def test_the_model_compares_no_setting_strings():
    methods = [m for _, m in inspect.getmembers(HOISDF, inspect.isfunction) if m.__qualname__.startswith("HOISDF.")]
    assert len(methods) >= 8
    found = {m.__name__: _string_compares(m) for m in methods}
    assert not any(found.values()), found
    # the finder finds switches where there are some
    assert _string_compares(B.query_sampler) == ["s.sampling == 'gradient'"]
    assert _string_compares(_is_str) == [] and _string_compares(mean_rotation)


def test_the_settings_choices_are_exactly_the_builders_parts():
    tables = {"sampling": B.TRAINING_ROWS, "cross_field": B.CROSS_FIELDS, "pose_regressor": REGRESSORS,
              "density_sign": B.DENSITY_SIGNS, "object_rotation": B.OBJECT_ROTATIONS}
    for key, table in tables.items():
        assert set(ModelSettings.CHOICES[key]) == set(table), key
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


def test_regressor_heads_are_registered_under_their_state_dict_names():
    for name, cls in REGRESSORS.items():
        model = B.build_model(load_train_config(None, TINY + [f'model.pose_regressor="{name}"']).model, None)
        heads = set(cls().heads(8, 1, 2, 16, 0.0))
        assert {k.split(".")[0] for k in model.state_dict()} >= heads
        assert not {k for k in model.state_dict() if k.startswith(("sampler.", "camera.", "regressor."))}


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
