"""Released checkpoints: ``hoisdf.import_upstream`` + ``load_model`` + forward equal upstream's own
``model(inputs, targets, meta_info, "eval")`` (amathislab/HOISDF @666e5b7, run in a scratch folder on the CPU).
The golden files (tests/golden/upstream/, see its README) hold upstream's key list with each key's seeded fill
rule, its MANO buffers and its outputs on deterministic inputs; the test rebuilds the same snapshot (upstream's
layout, ``module.`` keys) from the rules, so no 200 MB file is stored."""

from __future__ import annotations

import hashlib
import json
import tempfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from hoidata.errors import DataError
from hoisdf import import_upstream as CLI
from hoisdf.training import upstream as U
from hoisdf.training.checkpoint import load_model

GOLDEN = Path(__file__).parent / "golden" / "upstream"


def _draw(name: str, shape, kind: str, a, b) -> torch.Tensor:
    """The fill rule of the golden key list: generator seeded with crc32(name), then normal / uniform / int."""
    g = torch.Generator().manual_seed(zlib.crc32(name.encode()))
    if kind == "int":
        return torch.randint(int(a), int(b), tuple(shape), generator=g, dtype=torch.int64)
    if kind == "uniform":
        return (torch.rand(tuple(shape), generator=g, dtype=torch.float64) * (b - a) + a).float()
    return (torch.randn(tuple(shape), generator=g, dtype=torch.float64) * b + a).float()


def rebuild_network(setting: str, mano_dir) -> dict[str, torch.Tensor]:
    """Upstream's ``network`` dict for ``setting`` (``module.`` keys), rebuilt from the golden key list; the MANO
    buffers the project's (that they equal upstream's is test_mano_buffers_equal_upstreams' job alone)."""
    mano, network = U.mano_buffers(mano_dir), {}
    for name, shape, dtype, kind, a, b in _key_list(setting):
        value = mano[name.rpartition(".")[2]] if kind == "mano" else _draw(name, shape, kind, a, b)
        assert list(value.shape) == shape and str(value.dtype) == f"torch.{dtype}", name
        network[f"module.{name}"] = value
    return network


def write_snapshot(path: Path, network: dict) -> Path:
    torch.save({"epoch": 69, "network": network, "optimizer": {"state": {}, "param_groups": []}}, path)
    return path


def _batch(gold) -> dict:
    """The batch the evaluator builds, from the same inputs upstream saw (the image is redrawn from its seed)."""
    img = torch.rand(2, 3, 256, 256, generator=torch.Generator().manual_seed(2024))
    t = lambda k: torch.from_numpy(gold[k])  # noqa: E731
    return {"img": img, "K": t("meta.cam_intr"), "hand_root": t("meta.mano_root"),
            "obj_center": t("meta.obj_center_cam"), "hand_box": t("meta.bbox_hand"), "object_box": t("meta.bbox_obj")}


def _rodrigues(aa: torch.Tensor) -> torch.Tensor:
    angle = aa.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    k = aa / angle
    K = torch.zeros(*aa.shape[:-1], 3, 3, dtype=aa.dtype)
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - K.transpose(-1, -2)
    s, c = torch.sin(angle)[..., None], torch.cos(angle)[..., None]
    return torch.eye(3, dtype=aa.dtype) + s * K + (1 - c) * K @ K


def parity(run: Path, setting: str, mano_dir) -> dict[str, float]:
    """Max |difference| of each output between the imported model and upstream's golden outputs."""
    from hoidata.hand import load_mano

    gold = np.load(GOLDEN / f"golden_{setting}.npz")
    model, _ = load_model(run, load_mano(mano_dir, side="right"))
    with torch.no_grad():
        out = model(_batch(gold))
    g = {k: torch.from_numpy(gold[k]).double() for k in gold.files}
    rot_ref = _rodrigues(g["obj_rot_out"].mean(dim=1))  # upstream: mean of the 200 axis-angles, then Rodrigues
    chord = (out["obj_rotation"].double() - rot_ref).flatten(1).norm(dim=1)
    ik = "ik_joints" in g  # ho3d_render: the hand is upstream's test-time IK fit (main/test.py, ik_solver_mano)
    diffs = {"verts_m": out["verts"].double() - g["ik_verts" if ik else "mano_mesh_out"],
             "joints_m": out["joints"].double() - g["ik_joints" if ik else "mano_joints_out"],
             "vote_joints_m": out["vote_joints"][-1].double() - g["hand_joints_out"],
             "obj_translation_m": out["obj_translation"].double() - (g["meta.obj_center_cam"]
                                                                     + g["obj_trans_out"].mean(dim=1)),
             }
    if ik:
        diffs["betas"] = out["betas"][-1].double() - g["mano_shape_out"]
    result = {k: v.abs().max().item() for k, v in diffs.items()}
    for which in ("hand", "obj"):  # the same set of grid points (scaled units); upstream's order of near-ties
        ours, ref = out[f"{which}_query"].double() * model.scale, g[f"{which}_points"]  # (|SDF| within 1e-6) may differ
        match = torch.cdist(ours, ref)  # (B, N, N)
        result[f"{which}_query_set"] = max(match.min(dim=2).values.max().item(), match.min(dim=1).values.max().item())
        sdf_ref = g[f"{which}_points_sdf"][..., 0].abs()
        swapped = (ours - ref).abs().amax(-1) > 1e-5
        gap = (sdf_ref[swapped] - sdf_ref.gather(1, match.argmin(2))[swapped]).abs()
        result[f"{which}_query_order_gap"] = gap.max().item() if swapped.any() else 0.0
        if which == "obj":  # per-point rotations compared point by point: a near-tie swapped by the thread count's
            ref_rot = g["obj_rot_out"].gather(1, match.argmin(2)[..., None].expand(-1, -1, 3))  # summation order
            result["obj_rot_points_rad"] = (out["obj_rot_points"][-1].double() - ref_rot).abs().max().item()
    result["obj_rotation_rad"] = (2 * torch.asin((chord / (2 * 2 ** 0.5)).clamp(max=1))).max().item()
    return result


def lazily(root: Path, build):
    """key -> ``build(key, fresh folder under root)``, built once. A failed build fails the test that asked first;
    later requests are skipped naming its cause (before, its folder failed them all with FileExistsError)."""
    cache, failed = {}, {}

    def get(key):
        if key in failed:
            pytest.skip(f"building {key!r} failed in an earlier test: {failed[key]}")
        if key not in cache:
            try:
                cache[key] = build(key, Path(tempfile.mkdtemp(prefix=f"{key}-", dir=root)))
            except Exception as exc:
                failed[key] = f"{type(exc).__name__}: {exc}"
                raise
        return cache[key]
    return get


@pytest.fixture(scope="module")
def imported(tmp_path_factory, mano_dir):
    """setting -> (run folder, snapshot, import info) of the rebuilt snapshot, imported lazily once per setting."""
    def build(setting, tmp):
        snap = write_snapshot(tmp / "snapshot_69_1.pth.tar", rebuild_network(setting, mano_dir))
        return tmp / "run", snap, CLI.import_snapshot(snap, setting, mano_dir, tmp / "run")

    return lazily(tmp_path_factory.mktemp("upstream"), build)  # made in the set-up: removed with the module


def test_a_failed_build_fails_one_test_and_names_its_cause_to_the_others(tmp_path):
    def broken(key, folder):
        (folder / "run").mkdir()
        raise DataError(folder / "snap", "th_selected_comps", "differs")

    with pytest.raises(DataError):
        (get := lazily(tmp_path, broken))("dexycb")
    with pytest.raises(pytest.skip.Exception, match=r"'dexycb' failed in an earlier test: DataError: .*th_selected"):
        get("dexycb")
    ok = lazily(tmp_path, lambda key, folder: (folder / "run").mkdir() or folder)
    assert ok("dexycb") == ok("dexycb") != ok("ho3d") and ok("dexycb").parent == tmp_path  # once each, fresh folders


def test_mano_buffers_equal_upstreams(mano_dir):
    """The buffers the project computes from the toy MANO equal those upstream's manopth layer registered from
    it (``mano_buffers.npz``) within the key lists' tolerance (1e-6, as ``check_mano``): one test for a MANO fault."""
    mine, wrong, seen = U.mano_buffers(mano_dir), {}, set()
    for name, shape, dtype, kind, a, b in (row for s in ("dexycb", "ho3d", "ho3d_render") for row in _key_list(s)):
        if kind == "mano":
            buffer, seen = name.rpartition(".")[2], seen | {name.rpartition(".")[2]}
            want, got = torch.from_numpy(np.load(GOLDEN / a)[buffer]), mine[buffer]
            assert list(want.shape) == list(got.shape) == shape and str(got.dtype) == f"torch.{dtype}", name
            if not (diff := (got.double() - want.double()).abs().max().item()) <= b:
                wrong[buffer] = f"max |difference| {diff:.3g} > {b:g}"
    assert len(seen) == 9 and not wrong, (f"MANO buffers differ from upstream's manopth layer: {wrong}; the toy MANO "
                                          "(hoidata/toy/hand.py) changed or the golden is stale (its README)")


@pytest.mark.slow
@pytest.mark.parametrize("setting", ["dexycb", "ho3d", "ho3d_render"])
def test_imported_forward_equals_upstream(imported, mano_dir, setting):
    run, snap, info = imported(setting)
    diff = parity(run, setting, mano_dir)
    for key in ("vote_joints_m", "obj_translation_m", *(("verts_m", "joints_m") if setting != "ho3d_render" else ())):
        assert diff[key] < 1e-5, f"{setting}: {key} differs from upstream's golden by {diff[key]:.3g} (> 1e-5): {diff}"
    if setting == "ho3d_render":  # the IK fit: upstream adds 1e-7 to the norms and clamps cos to 1 - 1e-7, which bends
        assert diff["betas"] < 1e-5 and diff["joints_m"] < 2e-4 and diff["verts_m"] < 2e-4, diff  # near-zero angles
    assert diff["obj_rotation_rad"] < 1e-5 and diff["obj_rot_points_rad"] < 1e-5, diff
    assert diff["hand_query_set"] < 1e-6 and diff["obj_query_set"] < 1e-6, diff  # the same query points
    assert diff["hand_query_order_gap"] < 5e-6 and diff["obj_query_order_gap"] < 5e-6, diff  # order up to near-ties
    assert info["sha256"] == hashlib.sha256(snap.read_bytes()).hexdigest()


@pytest.mark.slow
def test_import_round_trip(imported, mano_dir):
    """The run folder holds the converted weights, the settings that reproduce upstream and the provenance."""
    from hoidata.hand import load_mano

    run, snap, info = imported("dexycb")
    network = torch.load(snap, map_location="cpu", weights_only=True)["network"]
    model, config = load_model(run, load_mano(mano_dir, side="right"))
    state = model.state_dict()
    for key, value in network.items():
        name = key.removeprefix("module.")
        if U.is_dropped(name):
            continue
        mine = state[U.project_key(name)]
        if name == "linear_pose.layers.2.bias" and config.model.rot6d == "offset":  # an identity-offset head
            value = value - torch.tensor(U.IDENTITY_6D)
        assert torch.equal(mine, value.reshape(mine.shape)), name
    m = config.model
    assert (m.pixel_convention, m.sheared_grid, m.normalize_input, m.density_sign, m.object_rotation, m.decoder) == \
        ("upstream", True, False, "code", "axis_angle", "small")
    assert m.rot6d == "raw"  # the preset's upstream recipe: upstream's raw 6D code, its bias copied unshifted
    written = json.loads((run / "config.json").read_text())["upstream"]
    assert written["sha256"] == info["sha256"] and written["setting"] == "dexycb" and written["epoch"] == 69
    assert len(written["dropped"]) == 26 and info["mapped"] == 699


def _key_list(setting):  # [name, shape, dtype, rule, a, b] per key
    return json.loads((GOLDEN / f"keys_{setting}.json").read_text())


def test_every_upstream_key_is_mapped_or_dropped():
    """Upstream's keys (golden lists) -> project names: a bijection onto the model, 26 dropped per setting."""
    from hoisdf.import_upstream import released_config
    from hoisdf.model import build_model

    for setting, n_mapped, n_dropped in (("dexycb", 699, 26), ("ho3d", 685, 26), ("ho3d_render", 693, 16)):
        keys = [k for k, *_ in _key_list(setting)]
        dropped = [k for k in keys if U.is_dropped(k)]
        mapped = {U.project_key(k, setting == "ho3d_render"): k for k in keys if not U.is_dropped(k)}
        assert len(dropped) == n_dropped and len(mapped) == n_mapped and None not in mapped
        with torch.device("meta"):
            expected = build_model(released_config(setting).model, None).state_dict()
        assert set(mapped) == set(expected)
        shapes = {k: s for k, s, *_ in _key_list(setting)}
        for new, old in mapped.items():
            assert list(expected[new].reshape(-1 if shapes[old] == [1] else expected[new].shape).shape) == shapes[old]
    for setting, arch in U.SETTINGS.items():  # the resolved settings of each --setting
        m = released_config(setting).model
        assert (m.decoder, m.pose_regressor) == (arch["decoder"], arch["pose_regressor"])
        assert (m.pixel_convention, m.sheared_grid, m.normalize_input, m.density_sign, m.object_rotation, m.weights) \
            == ("upstream", True, False, "code", "axis_angle", "")


def _zeros_network(setting="dexycb"):
    return {f"module.{k}": torch.zeros(s, dtype=getattr(torch, d)) for k, s, d, *_ in _key_list(setting)}


@pytest.mark.slow
def test_unexpected_missing_and_misshaped_keys_are_one_line():
    from hoisdf.import_upstream import released_config
    from hoisdf.model import build_model

    with torch.device("meta"):
        expected = build_model(released_config("dexycb").model, None).state_dict()
    network = _zeros_network()
    assert len(U.convert_network(network, expected, "snap")) == len(expected)
    extra = {**network, "module.linear_extra.layers.0.weight": torch.zeros(2, 2)}
    with pytest.raises(DataError, match=r"network\['module.linear_extra.layers.0.weight'\].*unexpected key"):
        U.convert_network(extra, expected, "snap")
    missing = {k: v for k, v in network.items() if k != "module.obj_sdf_decoder.linh4.bias"}
    with pytest.raises(DataError, match=r"1 weights missing.*obj_sdf.out_layer.bias"):
        U.convert_network(missing, expected, "snap")
    wrong = {**network, "module.linear_sdfin.layers.0.weight": torch.zeros(512, 3968)}  # a ho3d layer
    with pytest.raises(DataError, match=r"linear_sdfin.layers.0.weight.*shape \(512, 3968\).*\(512, 992\)"):
        U.convert_network(wrong, expected, "snap")
    ho3d = _zeros_network("ho3d")  # the big decoder's keys under --setting dexycb
    with pytest.raises(DataError, match="unexpected key|shape"):
        U.convert_network(ho3d, expected, "snap")


@pytest.mark.parametrize("value, words", [
    (torch.tensor([1.0, float("nan"), 2.0]), "3 values, 1 NaN"), (torch.tensor([float("inf"), float("nan")]),
                                                                    "1 NaN and 1 infinite"),
    (torch.tensor([1e39], dtype=torch.float64), "1 infinite (as torch.float32)"),  # finite until cast
    (torch.tensor([1, 2]), "torch.int64 values"), (torch.tensor([True]), "torch.bool values"),
    (torch.tensor([1 + 1j]), "complex"), (torch.tensor([1.5], dtype=torch.float16), None),
])
def test_checked_weight_refuses_what_a_cast_would_hide(value, words):
    if words is None:
        assert U.checked_weight(value, torch.float32, "s", "k").dtype == torch.float32
        return
    with pytest.raises(DataError, match=f"s: 'k': .*{__import__('re').escape(words)}"):
        U.checked_weight(value, torch.float32, "s", "k")
    ints = U.checked_weight(torch.tensor([3]), torch.int64, "s", "k")  # an integer buffer (num_batches_tracked)
    assert ints.dtype == torch.int64
    with pytest.raises(DataError, match="float values where integer ones belong"):
        U.checked_weight(torch.tensor([3.0]), torch.int64, "s", "k")


@pytest.mark.slow
@pytest.mark.parametrize("case", ["nan", "int64", "float16"])
def test_a_weight_that_is_not_finite_or_not_float_is_refused_naming_the_key(tmp_path, mano_dir, capsys, case):
    """NaN or infinity in one weight, or a float weight stored as integers or booleans, is refused naming the key
    (cast in silence, every prediction would be NaN or garbage); a narrower float (float16) imports, cast."""
    network = rebuild_network("dexycb", mano_dir)
    key = "module.backbone_net.resnet.conv1.weight"
    value = network[key].clone()
    if case == "nan":
        value.view(-1)[7] = float("nan")
    else:
        value = value.to({"int64": torch.int64, "float16": torch.float16}[case])
    snap = write_snapshot(tmp_path / "snapshot_1_1.pth.tar", {**network, key: value})
    code, err = _run_cli([snap, "--setting", "dexycb", "--mano", mano_dir, "--out", tmp_path / "run"], capsys)
    if case == "float16":
        assert code == 0 and (tmp_path / "run" / "checkpoints" / "last.pt").is_file(), err
        return
    words = {"nan": "1 NaN", "int64": "torch.int64 values"}[case]
    assert code == 2 and len(err.splitlines()) == 1 and f"network['{key}']" in err and words in err, err
    assert not (tmp_path / "run").exists()


def _run_cli(args, capsys):
    return CLI.main([str(a) for a in args]), capsys.readouterr().err.strip()


@pytest.mark.parametrize("case", ["text", "json", "truncated", "no_network", "code", "mano"])
def test_bad_snapshots_are_refused_in_one_line_and_write_nothing(tmp_path, mano_dir, capsys, case):
    snap = tmp_path / "snapshot_1_1.pth.tar"
    mano = {f"module.mano_head.mano_layer.{k}": v for k, v in U.mano_buffers(mano_dir).items()}
    if case == "text":
        snap.write_text("epoch: 7\n")
    elif case == "json":  # torch's weights_only story, cut mid-sentence, was the line once
        snap.write_text('{"network": {}}')
    elif case == "truncated":
        torch.save({"epoch": 1, "network": mano}, snap)
        snap.write_bytes(snap.read_bytes()[: snap.stat().st_size // 2])
    elif case == "no_network":
        torch.save({"epoch": 1, "model": mano}, snap)
    elif case == "code":  # a pickle that would construct an arbitrary object: weights_only refuses to run it
        torch.save({"epoch": 1, "network": mano, "extra": DataError("x", None, "y")}, snap)
    else:  # MANO buffers of other MANO files
        mano["module.mano_head.mano_layer.th_shapedirs"] = mano["module.mano_head.mano_layer.th_shapedirs"] * 1.01
        torch.save({"epoch": 1, "network": mano}, snap)
    code, err = _run_cli([snap, "--setting", "dexycb", "--mano", mano_dir, "--out", tmp_path / "run"], capsys)
    assert code == 2 and len(err.splitlines()) == 1 and str(snap) in err, err
    want = {"text": r"not a PyTorch checkpoint: it starts with 'epoch: 7\\n' \(text\?\)",
            "json": r"not a PyTorch checkpoint: it starts with '\{' \(JSON\?\)",
            "truncated": "not a readable PyTorch checkpoint", "no_network": "network",
            "code": "not a readable PyTorch checkpoint.*would run code", "mano": "th_shapedirs.*differs"}[case]
    assert __import__("re").search(want, err) and "weights_only" not in err and "Re-running" not in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_training_starts_from_imported_weights(tiny_store, mano_dir, tmp_path):
    """``hoisdf.train --init RUN``: the new run takes RUN's weights and [model] settings (here a tiny model with
    the released switches, as an imported run holds) and trains on; one AdamW step moves weights by ~lr only."""
    from hoidata.hand import load_mano
    from hoisdf.config import load_train_config
    from hoisdf.model import build_model
    from hoisdf.train import main
    from hoisdf.training.checkpoint import save_checkpoint

    tiny = ["model.depth=18", "model.image_size=64", "model.d_model=64", "model.ff=128", "model.hand_layers=1",
            "model.decoder_layers=1", "model.object_layers=1", "model.sdf_features=32", "model.sdf_hidden=96",
            "model.token_hidden=[48]", "model.hand_queries=32", "model.object_queries=16", "model.grid_resolution=16"]
    released = ['model.pixel_convention="upstream"', "model.sheared_grid=true", "model.normalize_input=false",
                'model.density_sign="code"', 'model.object_rotation="axis_angle"']
    cfg = load_train_config(None, tiny + released)
    torch.manual_seed(3)
    start = build_model(cfg.model, load_mano(mano_dir)).state_dict()
    save_checkpoint(tmp_path / "init" / "checkpoints" / "last.pt", {"model": start, "config": cfg.as_dict()})
    train = ["train.batch_size=2", "train.workers=0", "train.lr=1e-3", "train.shuffle_buffer=4", "train.val_every=0",
             "train.max_steps=1"]
    assert main(["--shards", str(tiny_store), "--mano", str(mano_dir), "--out", str(tmp_path / "ft"), "--no-progress",
                 "--init", str(tmp_path / "init"), *train]) == 0
    payload = torch.load(tmp_path / "ft" / "checkpoints" / "last.pt", weights_only=True)
    assert payload["config"]["model"] == cfg.as_dict()["model"] and payload["progress"]["global_step"] == 1
    moved = max((payload["model"][k] - v).abs().max().item() for k, v in start.items()
                if v.is_floating_point() and "running_" not in k)  # BatchNorm statistics follow the data
    assert 0 < moved < 5e-3


def test_tensors_saved_on_a_gpu_load_on_the_cpu(tmp_path, mano_dir, monkeypatch):
    """A snapshot whose storages are tagged "cuda:0" (as a GPU run writes them; the tag is forced here, this
    machine has no GPU) loads on the CPU: plain torch.load would fail without CUDA."""
    import torch.serialization

    network = {f"module.mano_head.mano_layer.{k}": v for k, v in U.mano_buffers(mano_dir).items()}
    monkeypatch.setattr(torch.serialization, "location_tag", lambda storage: "cuda:0")
    snap = write_snapshot(tmp_path / "snapshot_gpu.pth.tar", network)
    monkeypatch.undo()
    payload, _ = U.read_snapshot(snap)
    assert all(v.device.type == "cpu" for v in payload["network"].values())
    U.check_mano({k.removeprefix("module."): v for k, v in payload["network"].items()}, mano_dir, snap)


# upstream's loss names (eval mode, unweighted; main/train.py applies the weights) -> the project's terms
LOSS_NAMES = {"sdfhand_loss": "sdf_hand", "sdfobj_loss": "sdf_obj", "joint_heatmap": "heatmap", "hand_seg": "hand_seg",
              "obj_seg": "obj_seg", "loss_joint_3d": "joint_vote", "loss_joint_cls": "joint_cls",
              "loss_all_joint_3d": "joint_all", "mano_mesh_loss": "mano_verts", "mano_joint_loss": "mano_joints",
              "pose_param_loss": "mano_pose", "shape_param_loss": "mano_shape", "obj_rot": "obj_rot",
              "obj_trans": "obj_trans"}
LAMBDA_INSIDE = ("mano_mesh_loss", "mano_joint_loss", "pose_param_loss", "shape_param_loss")  # upstream ManoLoss


def _summed_gaussians(uv: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """Upstream's heatmap target / 255 (``Model.render_gaussian_heatmap``): the 21 Gaussians summed, not clipped."""
    grid = torch.arange(size, dtype=uv.dtype)
    g = torch.exp(-((grid[None, None, None, :] - uv[..., 0, None, None]) / sigma) ** 2 / 2
                  - ((grid[None, None, :, None] - uv[..., 1, None, None]) / sigma) ** 2 / 2)
    return g.sum(1, keepdim=True)


def loss_parity(run: Path, mano_dir, clip_heatmap: bool = False) -> dict[str, tuple[float, float]]:
    """{upstream name: (upstream value, project value)} on upstream's eval-mode batch (its SDF points, targets).

    ``clip_heatmap``: the project's own heatmap target (Gaussians summed and clipped at 1, ``render_heatmap``)
    instead of upstream's unclipped sum."""
    from hoidata.hand import load_mano
    from hoisdf.data.augment import render_heatmap
    from hoisdf.config import LossWeights
    from hoisdf.training.losses import HOISDFLoss

    gold = np.load(GOLDEN / "golden_dexycb.npz")
    t = lambda k: torch.from_numpy(gold[k]).float()  # noqa: E731
    mano = load_mano(mano_dir, side="right")
    model, _ = load_model(run, mano)
    batch = _batch(gold)
    root, center, scale = batch["hand_root"], batch["obj_center"], model.scale
    pose = torch.eye(4).repeat(2, 1, 1)
    pose[:, :3, :3] = _rodrigues(t("targets.obj_rot").double()).float()
    pose[:, :3, 3] = t("targets.rel_obj_trans") + center
    batch.update({  # upstream's scaled, centre-relative SDF rows and targets in this project's units and frames
        "hand_points": t("inputs.hand_sdf_points") / scale, "hand_sdf": t("targets.hand_sdf") / scale,
        "obj_points": t("inputs.obj_sdf_points") / scale + (center - root)[:, None],
        "obj_sdf": t("targets.obj_sdf") / scale,
        "heatmap": render_heatmap(t("targets.joint_coord"), 128, 1.25) if clip_heatmap else _summed_gaussians(
            t("targets.joint_coord"), 128, 1.25),
        "seg": torch.stack([t("targets.hand_seg"), t("targets.obj_seg")], 1),
        "joints_3d": t("targets.joint_cam_no_trans") / 1000 + root[:, None],
        "mano_pose": t("targets.mano_param")[:, :48], "mano_betas": t("targets.mano_param")[:, 48:],
        "object_pose": pose})
    with torch.no_grad():
        _, terms = HOISDFLoss(LossWeights(), mano)(model(batch), batch)
    out = {}
    for up, mine in LOSS_NAMES.items():
        w = 1.0 if up in LAMBDA_INSIDE else getattr(LossWeights(), mine)
        out[up] = (float(gold[up]), terms[mine].item() / w)
    return out


@pytest.mark.slow
def test_loss_terms_equal_upstream_eval_losses(imported, mano_dir):
    """Every loss term upstream's forward computes in eval mode (DexYCB: SDF at given points, 2D maps, voting, MANO,
    object) equals the project's term on the same batch, points and targets (relative 1e-4)."""
    run, _, _ = imported("dexycb")
    for name, (ref, mine) in loss_parity(run, mano_dir).items():
        assert mine == pytest.approx(ref, rel=1e-4, abs=1e-7), (name, ref, mine)
    # the project's own target clips overlapping Gaussians at 1 (its stores keep the map as 8-bit hm.png);
    # upstream sums them: on this batch the heatmap term reads 2.7 % lower
    ref, clipped = loss_parity(run, mano_dir, clip_heatmap=True)["joint_heatmap"]
    assert 0.95 < clipped / ref < 0.99


@pytest.mark.slow
def test_evaluate_accepts_an_imported_run(imported, tiny_store, dexycb_s0, mano_dir, tmp_path, capsys):
    """``python -m hoisdf.evaluate --ckpt RUN`` on an imported run, end to end with the usual result files: on a
    store of upstream's test crops (``record.crop="upstream"``) every record reaches the network as upstream's, and
    on a store of the project's crops the one-line note says what the imported weights are not seeing."""
    from hoidata.build_sdf import build_store
    from hoidata.records.settings import load_build_config
    from hoisdf.evaluate import main

    run, _, _ = imported("dexycb")
    upstream_store = tmp_path / "upstream_store"
    build_store(load_build_config("toy", ['dataset.splits=["test"]', "record.sdf_samples_hand=64", "record.sdf_samples_object=32",
                                          'record.crop="upstream"']),
                dexycb_s0, dexycb_s0 / "mano", dexycb_s0 / "models", upstream_store, progress=False)
    for store, out in ((upstream_store, tmp_path / "eval_upstream"), (tiny_store, tmp_path / "eval_project")):
        assert main(["--ckpt", str(run), "--shards", str(store), "--mano", str(mano_dir), "--out", str(out),
                     "--limit", "4", "--batch-size", "2", "--workers", "0", "--plausibility", "0",
                     "--no-progress"]) == 0
        metrics = json.loads((out / "metrics.json").read_text())
        assert (out / "per_object.csv").is_file() and metrics["samples"] == 4 and "MJE" in capsys.readouterr().out
        if store == upstream_store:
            assert metrics["upstream_crop_records"] == 4 and metrics["notes"] == []
        else:
            assert metrics["upstream_crop_records"] == 0 and len(metrics["notes"]) == 1
            assert "record.crop" in metrics["notes"][0]
