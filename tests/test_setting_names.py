"""Names that say what they count (issue 34): ``model.hand_queries`` / ``object_queries`` (the pose stage's query
points, once ``model.n_hand`` / ``n_object``) and ``train.sdf_rows_hand`` / ``sdf_rows_object`` (the SDF rows the
loader draws, once the model's value passed on by the trainer)."""

from __future__ import annotations

import pytest

from hoidata.errors import DataError
from hoisdf.config import TrainConfig, config_from_dict, load_train_config, overridden_config, sdf_rows


@pytest.mark.parametrize("old, new", [("n_hand", "hand_queries"), ("n_object", "object_queries")])
def test_an_old_key_in_an_override_is_one_line_naming_the_new_one(old, new):
    with pytest.raises(DataError, match=rf"model\.{old}.*an old name: this setting is now model\.{new}") as info:
        load_train_config(None, [f"model.{old}=32"])
    assert "\n" not in str(info.value) and "command line" in str(info.value)


def test_an_old_key_in_a_file_names_the_file_and_the_new_key(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text("[model]\ndepth = 18\nn_hand = 256\n")
    with pytest.raises(DataError, match=r"mine\.toml.*model\.n_hand.*model\.hand_queries"):
        load_train_config(str(path))


def test_a_checkpoint_config_with_the_old_keys_loads_as_the_new_ones():
    stored = TrainConfig().as_dict()
    stored["model"] = {k: v for k, v in stored["model"].items() if k not in ("hand_queries", "object_queries")}
    stored["model"].update(n_hand=48, n_object=24)
    before = {k: dict(v) for k, v in stored.items()}
    config = config_from_dict(stored, "old/last.pt")
    assert (config.model.hand_queries, config.model.object_queries) == (48, 24)
    assert stored == before  # the stored dict is left as it is
    assert config_from_dict(TrainConfig().as_dict()) == TrainConfig()
    with pytest.raises(DataError, match=r"model\.n_hand.*model\.hand_queries"):  # an override is refused, though
        overridden_config(stored, ["model.n_hand=8"], "old/config.json")
    assert overridden_config(stored, ["model.hand_queries=64"], "old/config.json").model.hand_queries == 64


def test_sdf_rows_default_to_the_query_counts_and_may_be_more():
    config = load_train_config(None, ["model.hand_queries=32", "model.object_queries=16"])
    assert (config.train.sdf_rows_hand, config.train.sdf_rows_object) == (0, 0)
    assert sdf_rows(config) == (32, 16)  # as upstream: as many rows as query points
    more = load_train_config(None, ["model.hand_queries=32", "model.object_queries=16", "train.sdf_rows_hand=100",
                                    "train.sdf_rows_object=20"])
    assert sdf_rows(more) == (100, 20)
    with pytest.raises(DataError, match=r"train\.sdf_rows_hand.*at least model\.hand_queries \(32\)"):
        load_train_config(None, ["model.hand_queries=32", "train.sdf_rows_hand=31"])
    with pytest.raises(DataError, match=r"train\.sdf_rows_object"):
        load_train_config(None, ["train.sdf_rows_object=-1"])


def test_both_commands_rename_through_one_table_per_settings_class():
    """The build's ``[record]`` and training's ``[model]`` renames are each the class's ``RENAMED``, refused by
    ``hoidata.sections`` in the same words, and read from what was written before by ``current_names``."""
    from hoidata.records.records import RecordSettings
    from hoidata.sections import current_names
    from hoisdf.config import ModelSettings

    assert ModelSettings.RENAMED == {"n_hand": "hand_queries", "n_object": "object_queries"}
    assert RecordSettings.RENAMED == {"n_hand": "sdf_samples_hand", "n_object": "sdf_samples_object"}
    stored = {"n_hand": 48, "depth": 18}
    assert current_names(stored, ModelSettings.RENAMED) == {"depth": 18, "hand_queries": 48}
    assert stored == {"n_hand": 48, "depth": 18}  # left as it is
    # where the new name is present too (written by both a new and an old writer), the new name's value wins
    assert current_names({"n_hand": 1, "hand_queries": 2}, ModelSettings.RENAMED) == {"hand_queries": 2}
    assert current_names({"depth": 18}, ModelSettings.RENAMED) == {"depth": 18}


def test_a_setting_prints_as_toml_writes_it():
    from hoidata.sections import toml_value

    assert [toml_value(v) for v in (True, "upstream", (1, 2.5), ["a", False], 0.1, 600)] == [
        "true", '"upstream"', "[1, 2.5]", '["a", false]', "0.1", "600"]


@pytest.mark.parametrize("override, key", [("train.lr=-1", "train.lr"), ("model.heads=0", "model.heads"),
                                           ("loss.heatmap=-2", "loss.heatmap"), ("augment.scale_sigma=-1", "augment.scale_sigma")])
def test_a_bad_value_from_the_command_line_names_the_override_beside_the_file(override, key):
    with pytest.raises(DataError) as info:
        load_train_config("toy", [override])
    text = str(info.value)
    assert f"toy.toml with the command line's {override}" in text and repr(key) in text and "\n" not in text


def test_a_rename_in_any_training_section_is_read_from_checkpoints_and_refused_in_overrides(monkeypatch):
    """The renames are the settings classes' own tables, not a list of model keys: a key renamed in [train] (made up
    here) reads from a stored config and is one line in a file's override or a run's override alike."""
    from hoisdf.config import TrainSettings

    monkeypatch.setattr(TrainSettings, "RENAMED", {"learning_rate": "lr"}, raising=False)
    stored = TrainConfig().as_dict()
    stored["train"] = {k: v for k, v in stored["train"].items() if k != "lr"} | {"learning_rate": 3e-4}
    assert config_from_dict(stored, "old/last.pt").train.lr == 3e-4
    assert "learning_rate" in stored["train"]  # the stored dict is left as it is
    with pytest.raises(DataError, match=r"train\.learning_rate.*this setting is now train\.lr"):
        overridden_config(stored, ["train.learning_rate=1e-3"], "old/config.json")
    with pytest.raises(DataError, match=r"command line's train\.learning_rate=1e-3.*this setting is now train\.lr"):
        load_train_config("toy", ["train.learning_rate=1e-3"])
