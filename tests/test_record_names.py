"""``[record]`` settings named for what they count (issue 34): ``record.sdf_samples_hand`` / ``sdf_samples_object``
replace ``n_hand`` / ``n_object``. An old key in a file or on the command line is one line naming the new key;
a store or export started under the old names resumes; the crop policy is chosen once from the settings."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from hoidata.errors import DataError
from hoidata.records import CropPolicy, RecordSettings, fingerprint, load_build_config
from hoidata.records.store_writer import BUILD_FILE, check_build_file


def _toml(tmp_path, text: str) -> str:
    path = tmp_path / "p.toml"
    path.write_text('[dataset]\nname = "dexycb"\n' + text)
    return str(path)


@pytest.mark.parametrize("old,new", [("n_hand", "sdf_samples_hand"), ("n_object", "sdf_samples_object")])
def test_an_old_key_in_a_file_names_the_new_one(tmp_path, old, new):
    path = _toml(tmp_path, f"[record]\n{old} = 64\n")
    with pytest.raises(DataError, match=rf"p\.toml: 'record\.{old}': an old name: this setting is now record\.{new}"):
        load_build_config(path)
    assert getattr(load_build_config(_toml(tmp_path, f"[record]\n{new} = 64\n")).record, new) == 64


def test_an_old_key_on_the_command_line_names_the_override_and_the_new_key(tmp_path):
    with pytest.raises(DataError, match=r"command line's record\.n_hand=8: 'record\.n_hand': an old name: this setting "
                                        r"is now record\.sdf_samples_hand") as err:
        load_build_config("toy", ["record.n_hand=8"])
    assert len(str(err.value).splitlines()) == 1


def test_the_sampling_settings_map_the_new_names():
    sampling = RecordSettings(sdf_samples_hand=300, sdf_samples_object=200).sdf_sampling()
    assert (sampling.n_hand, sampling.n_object) == (300, 200)


def _old_names(spec: dict) -> dict:
    record = {_old(k): v for k, v in spec["config"]["record"].items()}
    return {**spec, "config": {**spec["config"], "record": record}}


def _old(key: str) -> str:
    return {new: old for old, new in RecordSettings.RENAMED.items()}.get(key, key)


def test_a_store_pinned_under_the_old_names_resumes_and_still_refuses_another_value(tmp_path):
    config = load_build_config("toy").as_dict()
    check_build_file(tmp_path, config, ["a", "b"], {"mano": {}})
    path = tmp_path / BUILD_FILE
    written = json.loads(path.read_text())
    path.write_text(json.dumps(_old_names(written)))  # build.json as a build before the rename wrote it
    assert "n_hand" in json.loads(path.read_text())["config"]["record"]
    check_build_file(tmp_path, config, ["a", "b"], {"mano": {}})  # the same settings: resumes
    other = load_build_config("toy", ["record.sdf_samples_hand=100"]).as_dict()
    with pytest.raises(DataError, match=r"record\.sdf_samples_hand differs from the one this store was started with"):
        check_build_file(tmp_path, other, ["a", "b"], {"mano": {}})
    assert "n_hand" in json.loads(path.read_text())["config"]["record"]  # nothing rewritten


def test_current_names_leaves_other_specs_as_they_are():
    renamed = RecordSettings.RENAMED
    assert fingerprint.current_names({"config": {"record": {"crop_size": 1}}}, renamed) == {
        "config": {"record": {"crop_size": 1}}}
    assert fingerprint.current_names({"frames": 3}, renamed) == {"frames": 3}
    assert fingerprint.current_names({"config": {"record": {"n_object": 5}}}, renamed) == {
        "config": {"record": {"sdf_samples_object": 5}}}


def _frame(split: str, labelled: bool = True):
    return SimpleNamespace(split=split, has_hand_pose=labelled)


def test_the_crop_policy_is_read_from_the_settings_once():
    project = RecordSettings(crop_size=128).crop_policy()
    assert project == CropPolicy(128, False, ("test", "evaluation"), ())
    assert not project.upstream_crop(_frame("test")) and project.record_size(_frame("test")) == 128
    assert not project.needs_points and not project.reads_object_folders
    upstream = RecordSettings(crop="upstream", crop_splits=("test",), upstream_region=("train",)).crop_policy()
    assert upstream.upstream_crop(_frame("test")) and not upstream.upstream_crop(_frame("train"))
    assert upstream.record_size(_frame("test")) == 256  # upstream's input size
    assert upstream.upstream_region(_frame("train")) and not upstream.upstream_region(_frame("train", labelled=False))
    assert upstream.needs_points and upstream.reads_object_folders
    region = RecordSettings(upstream_region=("train",)).crop_policy()
    assert region.needs_points and not region.reads_object_folders and not region.upstream_crop(_frame("test"))


@pytest.mark.slow  # builds a store of the tiny toy DexYCB
def test_a_built_store_pinned_under_the_old_names_resumes_whole_and_verifies(tiny_dexycb, tmp_path):
    from hoidata import store
    from hoidata.build_sdf import build_store

    cfg = load_build_config("toy", ['dataset.splits=["train"]', "record.crop_size=64", "record.sdf_samples_hand=32",
                                    "record.sdf_samples_object=32", "store.records_per_shard=8"])
    out = tmp_path / "store"
    first = build_store(cfg, tiny_dexycb, tiny_dexycb / "mano", tiny_dexycb / "models", out, progress=False)
    path = out / BUILD_FILE
    path.write_text(json.dumps(_old_names(json.loads(path.read_text()))))  # as a build before the rename left it
    again = build_store(cfg, tiny_dexycb, tiny_dexycb / "mano", tiny_dexycb / "models", out, progress=False)
    assert first.finished and (again.units_kept, again.units_written) == (len(first.units), 0)
    assert again.finished and again.finish_kept and store.verify_store(out).ok
