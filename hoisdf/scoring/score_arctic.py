"""``hoisdf score arctic``: an ARCTIC leaderboard submission (pose or field task) scored offline against a
ground-truth folder, as ARCTIC's ``scripts_method/evaluate_metrics.py`` scores it on its server; and the check
behind ``hoisdf check arctic`` (docs/scoring.md, "ARCTIC").

Posing, as the server does: predicted MANO rotations (matrices) to axis-angle as PyTorch3D 0.7.3 converts them
(:func:`hoidata.geometry.rotation.matrix_to_axis_angle_as_pytorch3d`),
MANO with ``flat_hand_mean=False`` and no left-hand shape fix, no translation, then ``cam_t`` added; 21 joints
(16 MANO joints, fingertip vertices 744, 320, 443, 554, 671); the object template posed by its articulation and
axis-angle, then ``cam_t`` added. The ground truth the same way from its axis-angle poses. Predictions longer
than the ground truth are cut; the ground truth's frames and image names are the ones scored.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from hoidata.errors import DataError
from hoidata.objects.arctic import load_arctic_object, pose_object, read_object_meta
from hoisdf.scoring import arctic_metrics as am
from hoisdf.scoring.arctic_files import Source, check_submission, read_ground_truth, read_reference

HELP = "ARCTIC leaderboard submission (pose or field task) against a ground-truth folder"
TIPS = (744, 320, 443, 554, 671)
POSE_ORDER = ("aae", "mpjpe/ra/h", "mrrpe/r/l", "mrrpe/r/o", "success_rate/0.05", "cdev/ho", "mdev/h", "acc/h", "acc/o")
FIELD_ORDER = ("avg/ho", "avg/oh", "acc/ho", "acc/oh")
UNITS = {"aae": "deg", "success_rate/0.05": "%", "acc/h": "m/s^2", "acc/o": "m/s^2", "acc/ho": "m/s^2",
         "acc/oh": "m/s^2"}


def add_arguments(p) -> None:
    p.add_argument("--pred", required=True, type=Path, metavar="DIR|ZIP", help="the submission (<task>_<setup>_test)")
    p.add_argument("--gt", required=True, type=Path, metavar="DIR",
                   help="ground truth: <sXX>_<sequence>_<view>/{targets,meta_info}/*.pt (ARCTIC's eval extraction)")
    p.add_argument("--meta", required=True, type=Path, metavar="DIR",
                   help="ARCTIC's meta folder (object_vtemplates/, object_meta.json)")
    p.add_argument("--mano", type=Path, default=None, metavar="DIR",
                   help="MANO folder (default: META/../../body_models/mano)")
    add_task_arguments(p)


def add_task_arguments(p) -> None:
    p.add_argument("--task", choices=("pose", "field"), default=None, help="default: from the submission's name")
    p.add_argument("--setup", choices=("p1", "p2"), default=None, help="p1 allocentric, p2 egocentric (default: "
                                                                       "from the submission's name)")


def task_and_setup(pred: Path, task: str | None, setup: str | None) -> tuple[str, str]:
    """The task and setup given, else read from a ``<task>_<setup>_test`` name in the submission's path or in its
    one top folder."""
    names = [pred.stem, pred.name]
    try:
        source = Source(pred)
        names += sorted({n.split("/")[0] for n in source.names})
    except DataError:
        pass
    for name in names:
        found = re.match(r"^(pose|field)_(p1|p2)_", name)
        if found:
            task, setup = task or found.group(1), setup or found.group(2)
            break
    if task is None or setup is None:
        raise DataError(pred, None, "cannot tell the task and setup from its name: give --task and --setup")
    return task, setup


class Models:
    """MANO right and left (float64, ``flat_hand_mean=False`` by adding ``hands_mean``, no left shape fix) and
    ARCTIC's object templates, loaded once."""

    def __init__(self, mano_dir: Path, meta: Path):
        import torch  # the MANO layer is torch's; this module imports it only to pose hands

        from hoidata.hand import load_mano

        self.torch = torch
        self.mano = {s[0]: load_mano(mano_dir, side=s, fix_left_shapedirs=False, dtype=torch.float64)
                     for s in ("right", "left")}
        self.meta, self.diameters, self.objects = meta, read_object_meta(meta), {}

    def object(self, name: str):
        if name not in self.objects:
            self.objects[name] = load_arctic_object(self.meta, name, self.diameters)
        return self.objects[name]

    def axis_angle(self, matrices: np.ndarray) -> np.ndarray:
        """(N, 16 x 9) submitted rotation matrices -> (N, 48) axis-angle, as the server converts them."""
        from hoidata.geometry.rotation import matrix_to_axis_angle_as_pytorch3d

        m = self.torch.as_tensor(np.asarray(matrices, np.float64).reshape(-1, 16, 3, 3))
        return matrix_to_axis_angle_as_pytorch3d(m).numpy().reshape(-1, 48)

    def hand(self, side: str, pose_aa: np.ndarray, betas: np.ndarray, cam_t: np.ndarray):
        mano = self.mano[side]
        flat = np.array(pose_aa, np.float64).reshape(-1, 48)
        flat[:, 3:] += mano.hands_mean.double().numpy()
        zero = np.zeros((len(flat), 3))
        with self.torch.no_grad():
            out = mano(self.torch.as_tensor(flat), self.torch.as_tensor(np.asarray(betas, np.float64)),
                       self.torch.as_tensor(zero))
        v = out.vertices.double().numpy()
        j = np.concatenate([out.mano_joints.double().numpy(), v[:, list(TIPS)]], 1)
        return v + cam_t[:, None], j + cam_t[:, None]


def posed(models: Models, values: dict, obj, prefix: str, matrices: bool) -> dict:
    """Vertices and joints of both hands and the object's vertices from one side's files (``pred.`` or
    ``targets.`` keys stripped to ``mano.pose.r`` ...)."""
    out = {}
    for s in ("r", "l"):
        pose = values[f"{prefix}mano.pose.{s}"]
        pose = models.axis_angle(pose) if matrices else pose
        betas, cam_t = values[f"{prefix}mano.beta.{s}"], values[f"{prefix}mano.cam_t.{s}"]
        out[f"v.{s}"], out[f"j.{s}"] = models.hand(s, pose, betas, cam_t)
    radian = values[f"{prefix}object.radian"]
    out["v.o"] = pose_object(obj, radian, values[f"{prefix}object.rot"]) + values[f"{prefix}object.cam_t"][:, None]
    out["radian"] = radian
    return out


def check(args) -> tuple[list[str], list[str], dict, dict | None, str, str]:
    """Problems, notes and predictions of ``args.pred`` (against ``args.gt`` when given), and the reference."""
    task, setup = task_and_setup(args.pred, args.task, args.setup)
    reference = read_reference(args.gt) if getattr(args, "gt", None) else None
    vertices = None
    if getattr(args, "meta", None) is not None and task == "field":
        diameters = read_object_meta(args.meta)
        names = {f.split("_")[1] for f in (reference or {})} or set(diameters)
        vertices = {n: len(load_arctic_object(args.meta, n, diameters).vertices) for n in names}
    problems, notes, preds = check_submission(args.pred, task, setup, reference, vertices)
    return problems, notes, preds, reference, task, setup


def score(args) -> dict:
    """The pooled metrics of ``args.pred`` (docs/scoring.md, "ARCTIC"), with ``samples`` (frames), counts of
    contact windows and of (sequence, view, hand) without one, and the notes of the check."""
    problems, notes, preds, reference, task, setup = check(args)
    if problems:
        more = f" ({len(problems) - 1} more problems: hoisdf check arctic lists them)" if len(problems) > 1 else ""
        raise DataError(None, None, problems[0] + more)
    mano_dir = args.mano or Path(args.meta).resolve().parent.parent.parent / "body_models" / "mano"
    models = Models(mano_dir, args.meta)
    parts, windows, no_window, first_frame, frames = [], 0, 0, 0, 0
    gt_files = Source(args.gt)
    for name in sorted(reference):
        gt = read_ground_truth(gt_files, name)
        targets, obj = gt["targets"], models.object(gt["object"])
        flags = {k: targets[k] for k in ("is_valid", "left_valid", "right_valid")}
        g = posed(models, {f"t.{k}": v for k, v in targets.items()}, obj, "t.", matrices=False)
        field = am.interaction_field(g["v.r"], g["v.l"], g["v.o"])
        if task == "field":
            pred = {k.replace("pred.", ""): v for k, v in preds[name].items()}
            parts.append(am.field_metrics(pred, {k: field[k] for k in pred}, flags))
        else:
            p = posed(models, preds[name], obj, "pred.", matrices=True)
            metrics = am.pose_metrics(p, {**g, **flags}, obj.part_ids, obj.diameter, field)
            mdev = []
            valid = flags["is_valid"]
            for s, hv in (("r", flags["right_valid"] * valid), ("l", flags["left_valid"] * valid)):
                found, stops = am.find_windows(field[f"dist.{s}o"], field[f"idx.{s}o"], g["v.o"][0])
                windows, no_window, first_frame = windows + len(found), no_window + (not found), first_frame + stops
                mdev.append(am.motion_deviation(found, p[f"v.{s}"], p["v.o"], hv))
            metrics["mdev/h"] = np.concatenate(mdev)
            parts.append(metrics)
        frames += gt["frames"]
    order = POSE_ORDER if task == "pose" else FIELD_ORDER
    pooled = am.pool(parts)
    out = {k: pooled[k] for k in order}
    extra = {"contact_windows": windows, "hands_without_window": no_window, "windows_at_first_frame": first_frame} \
        if task == "pose" else {}
    note = ("scored as ARCTIC's evaluate_metrics.py; the leaderboard's test ground truth stays on its server"
            + (f"; {no_window} (sequence, view, hand) without a contact window (ARCTIC's code stops there)"
               if no_window else "") + (f"; {first_frame} window(s) starting at the first frame (ARCTIC's check "
                                        "stops there)" if first_frame else ""))
    return {**out, **extra, "task": f"{task}_{setup}", "folders": len(reference), "samples": frames,
            "official": False, "note": note, "notes": notes, "pred_file": str(args.pred), "ground_truth": str(args.gt)}


def format_result(result: dict) -> str:
    lines = [f"ARCTIC {result['task']} scores of {result['pred_file']} ({result['folders']} sequence views, "
             f"{result['samples']} frames)", f"  {result['note']}"]
    lines += [f"  note: {n}" for n in result["notes"]]
    for key in POSE_ORDER + FIELD_ORDER:
        if key in result:
            lines.append(f"  {key:<20} {result[key]:12.6f} {UNITS.get(key, 'mm')}")
    for key in ("contact_windows", "hands_without_window", "windows_at_first_frame"):
        if key in result:
            lines.append(f"  {key:<24} {result[key]}")
    return "\n".join(lines)

