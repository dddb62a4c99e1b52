"""The ``canrig`` command: one path from a head file and a phone capture to an animated rig.

Subcommands (``canrig SUBCOMMAND --help`` for each):

- ``canrig autorig HEAD -o rig.glb``: RigAnyFace on a head file (OBJ, PLY, glTF, GLB), or on
  a whole avatar (a skinned GLB or FBX, a VRM 1.0): the same avatar with a face rig.
- ``canrig animate RIG TAKE.csv -o anim.glb``: drive a rig from a Live Link Face CSV.
- ``canrig invert RIG MESHES -o take.csv``: the inverse rig of a mesh sequence (a folder of
  OBJ files or an ``.npz``) written as a Live Link Face CSV.
- ``canrig retarget TAKE.csv --from RIG --to-set SET -o out.csv``: a take carried onto
  another control set of the same mesh (ARKit -> SRanipal, FACS, ...) as .csv or .glb.
- ``canrig correct RIG EDITS -o rig.glb``: WPSE from sculpted frames, baked into the glTF.
- ``canrig view FILE.glb [--port N]``: a local web viewer (127.0.0.1 only) for a rig or take;
  ``--screenshot OUT.png --time T`` renders one frame in headless Chromium instead.

Errors in the inputs are reported as one ``canrig: error: ...`` line naming the file (exit
status 2); nothing partial is written (every output is written atomically, after the work is
done). Warnings are ``canrig: warning: ...`` lines, each message once; progress lines
(``[  12.3 s] ...``) go to standard error too, and ``--quiet`` silences only those.
"""

import argparse
import dataclasses
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from . import watchdog
from ._cli import add_dataclass_options, from_args
from ._warnings import CanrigWarning, print_warnings

INVERSE_METHODS = {
    "quartic": "QuarticCD",
    "linear": "LinearCD",
    "seol": "Seol",
    "joshi": "Joshi",
    "cetinaslan": "Cetinaslan",
    "lmmm": "LMMM",
    "lbfgsb": "JaxoptLBFGSB",
}
"""``--method`` values of ``canrig invert`` and the ``canrig_jax.inverse`` class of each."""
AUTORIG_METHODS = {
    "transfer": "Transfer",
    "raf": "RigAnyFaceNetwork",
    "transfer-residual": "TransferResidual",
}
"""``--method`` values of ``canrig autorig`` and the ``canrig_jax.autorig`` method class of each
(``AbstractAutoRigMethod``; the name is the class's ``name``)."""


class CommandError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def _warn(message: str) -> None:
    """A warning of the command itself: one ``canrig: warning: ...`` line (see ``main``)."""
    warnings.warn(message, CanrigWarning, stacklevel=2)


class _Parser(argparse.ArgumentParser):
    """argparse with the command's error line: usage, then ``canrig: error: ...``."""

    def error(self, message: str):
        self.print_usage(sys.stderr)
        self.exit(2, f"canrig: error: {message}\n")


class _Progress:
    """Stage messages with elapsed seconds on stderr (silenced by ``--quiet``); each is
    progress for the watchdog."""

    def __init__(self, quiet: bool):
        self.quiet, self.start = quiet, time.perf_counter()

    def __call__(self, message: str) -> None:
        watchdog.progress(message)
        if not self.quiet:
            print(f"[{time.perf_counter() - self.start:6.1f} s] {message}", file=sys.stderr)


def _output(path: str, suffixes: Sequence[str]) -> Path:
    """An output path whose folder exists and whose extension is one of ``suffixes``."""
    out = Path(path)
    if out.suffix.lower() not in suffixes:
        raise CommandError(f"-o {out}: expected a {' or '.join(suffixes)} file name")
    if out.is_dir():
        raise CommandError(f"-o {out}: is a folder, expected a file name")
    if not out.parent.is_dir():
        raise CommandError(f"-o {out}: the folder {out.parent} does not exist")
    return out


def _input(path: str, what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise CommandError(f"{what} {p}: not found")
    return p


def _load_rig(path: str, what: str = "RIG", *, crop: str | None = None):
    """A rig from a ``.glb`` written by canrig (``load_gltf_rig``), a ``.npz`` (a rig of
    ``save_rig``, or shapes: ``neutral``, ``deltas``, ``names``, optional ``faces`` and
    ``units``) or an ``.fbx`` (``load_fbx_rig``: its ARKit shapes; ``crop="head"`` cuts a
    whole body to the head)."""
    from .data import read_arrays
    from .rig import BlendshapeRig, load_fbx_rig, load_gltf_rig, load_rig

    p = _input(path, what)
    suffix = p.suffix.lower()
    if suffix == ".glb":
        return load_gltf_rig(p)
    if suffix == ".fbx":
        return load_fbx_rig(p, crop=crop)
    if suffix == ".npz":
        with np.load(p, allow_pickle=False) as z:
            keys = set(z.files)
        if "orders" in keys:
            return load_rig(p)
        if {"neutral", "deltas", "names"} <= keys:
            optional = [k for k in ("faces", "units") if k in keys]
            z = read_arrays(p, ["neutral", "deltas", "names", *optional])
            return BlendshapeRig(
                z["neutral"],
                z["deltas"],
                (),
                tuple(str(n) for n in z["names"]),
                z.get("faces"),
                str(z["units"]) if "units" in z else "cm",
            )
        raise CommandError(
            f"{what} {p}: an .npz rig needs save_rig's arrays or neutral, deltas and names"
        )
    raise CommandError(f"{what} {p}: expected a .glb (canrig autorig), a .npz or an .fbx rig")


def _arkit_columns(rig) -> tuple[np.ndarray, list[str]]:
    """(K_rig, K_csv) matrix mapping a rig's weights onto the Live Link Face channels it drives
    (ICT halves averaged) and those channel names."""
    from .data import LIVELINK_CSV_CHANNELS, arkit_name_of, retarget_weights, to_arkit

    present = {arkit_name_of(str(n)) for n in rig.names} - {None}
    channels = [c for c in LIVELINK_CSV_CHANNELS if to_arkit(c) in present]
    eye = np.eye(rig.n_blendshapes, dtype=np.float32)
    mixing, _ = retarget_weights(eye, rig.names, channels)
    return mixing, channels


# ---------------------------------------------------------------------------------- autorig
def _autorig(args) -> None:
    from . import autorig
    from .data import load_head
    from .rig import check_extra_sets, export_gltf, with_extra_shapes

    out = _output(args.output, (".glb", ".vrm", ".usda", ".usdc", ".usd"))
    method_class, model_path = _autorig_method_class(args)
    if (args.up is None) != (args.forward is None):
        raise CommandError("--up, --forward: state both of the head's axes or neither")
    progress = _Progress(args.quiet)
    try:
        args.extras = check_extra_sets(args.extras or ())
    except ValueError as error:
        raise CommandError(f"--extras {','.join(args.extras)}: {error}") from None
    if _is_avatar(_input(args.head, "HEAD")):
        _autorig_avatar(args, out, progress)
        return
    if args.replace:
        raise CommandError("--replace: only an avatar's meshes hold morph targets to replace")
    if out.suffix.lower() == ".vrm":
        raise CommandError(f"-o {out}: a .vrm is written from a whole avatar (a skeleton)")
    usd = out.suffix.lower() in (".usda", ".usdc", ".usd")
    head = load_head(_input(args.head, "HEAD"), units=args.units)
    progress(
        f"read {head.path}: {len(head.vertices)} vertices, {len(head.faces)} triangles, "
        f"units {head.units}{' (inferred)' if head.inferred else ''}, {head.size_cm:.1f} cm tall"
    )
    examples = None
    if args.examples:
        examples = _load_rig(args.examples, "--examples")
        if examples.n_vertices != len(head.vertices):
            raise CommandError(
                f"--examples {args.examples}: {examples.n_vertices} vertices, the head has "
                f"{len(head.vertices)}: examples must be sculpted on the head's own mesh"
            )
        progress(f"read {examples.n_blendshapes} example shapes: {', '.join(examples.names)}")
    dataset = None  # the network method needs no data folder
    if method_class.needs_landmarks:
        progress("loading the ICT source rig")
        dataset = autorig.ict_pose_source(progress=False)
    method = _autorig_method(args, method_class, model_path, dataset, progress)
    try:
        result = autorig.auto_rig(
            head.vertices_in("cm"),
            head.faces,
            method=method,
            dataset=dataset,
            examples=examples,
            up=args.up,
            forward=args.forward,
            names="source" if args.names == "ict" else "arkit",
            progress=progress,
        )
    except autorig.OrientationError as error:
        message = str(error).replace("vertices: ", "", 1)
        raise CommandError(f"HEAD {head.path}: {message}") from error
    except ValueError as error:
        if "examples" in str(error).split(":")[0]:
            raise CommandError(f"--examples {args.examples}: {error}") from error
        raise
    rig = with_extra_shapes(result.rig, args.extras) if args.extras else result.rig
    turned = "" if result.orientation.conventional else " (the rig stays in the head's frame)"
    progress(f"orientation: {result.orientation.describe()}{turned}")
    progress(
        f"generated {rig.n_blendshapes} blendshapes ({args.names} names) and "
        f"{sum(int(c.indices.shape[0]) for c in rig.correctives)} correctives with "
        f"{result.method} in {result.seconds['total']:.1f} s"
    )
    _check_generated(result, args, progress)
    if usd:
        from .rig import export_usd

        export_usd(rig, out)
        progress(f"wrote {out}: UsdSkel blend shapes, centimetres (correctives not written)")
        return
    export_gltf(rig, out)
    progress(f"wrote {out} (centimetres)")


def _autorig_method_class(args):
    """(the ``autorig`` method class ``--method`` names, its checkpoint path or None), with
    ``--model`` and ``--template`` checked against it."""
    from . import autorig

    if args.method is None:
        args.method = autorig.Transfer.name if args.template else autorig.DEFAULT_METHOD.name
    method_class = getattr(autorig, AUTORIG_METHODS[args.method])
    model_path = None
    if issubclass(method_class, autorig.AbstractNetworkMethod):
        model_path = Path(args.model) if args.model else method_class.checkpoint
        if not model_path.is_file():
            raise CommandError(f"--model {model_path}: RigAnyFace checkpoint not found")
    elif args.model:
        raise CommandError(f"--model: --method {args.method} uses no network")
    if args.template and method_class is not autorig.Transfer:
        raise CommandError("--template: only --method transfer carries a template")
    return method_class, model_path


def _autorig_method(args, method_class, model_path, dataset, progress):
    """The ``autorig`` method object of ``--method`` (with ``--template`` or ``--model``)."""
    from . import autorig

    if args.template:
        rig = _load_rig(args.template, "--template", crop="head")
        progress(f"fitting the template {args.template} ({rig.n_blendshapes} shapes)")
        try:
            template = autorig.Template.from_rig(dataset, rig, Path(args.template).name)
        except ValueError as error:
            raise CommandError(f"--template {args.template}: {error}") from error
        return autorig.Transfer(template=template)
    if model_path is not None:
        progress(f"loading the network {model_path}")
        try:
            return method_class(model=autorig.load_riganyface(model_path)[:2])
        except ValueError as error:
            raise CommandError(f"--model {model_path}: {error}") from error
    return method_class()


def _check_generated(result, args, progress) -> None:
    """``canrig autorig``'s rigger's checks of a generated rig, on random sparse poses of its
    own shapes: the summary printed; a failed hard check is a warning naming it, or with
    ``--strict`` an error (nothing written)."""
    from .autorig._any_head import check_auto_rig
    from .autorig._rig_checks import failed_hard_checks

    if args.no_check:
        return
    progress("checking the rig (canrig check: blink, jaw, eyes, teeth, flips, crossings)")
    report = check_auto_rig(result)
    progress(report.summary())
    if report.ok:
        return
    failed = failed_hard_checks(report)
    if args.strict:
        raise CommandError(f"HEAD {args.head}: the rig fails hard checks: {failed}; not written")
    _warn(f"the rig fails hard checks: {failed} (canrig check RIG prints the table)")


def _check(args) -> int:
    from . import autorig

    progress = _Progress(args.quiet)
    rig = _load_rig(args.rig, crop="head")
    if args.head:
        from .data import load_head

        head = load_head(_input(args.head, "--head"))
        if len(head.vertices) != rig.n_vertices:
            raise CommandError(
                f"--head {args.head}: {len(head.vertices)} vertices, the rig has {rig.n_vertices}"
            )
        rig = type(rig)(rig.neutral, rig.deltas, rig.correctives, rig.names, head.faces, rig.units)
    progress(f"read {args.rig}: {rig.n_blendshapes} blendshapes, {rig.n_vertices} vertices")
    poses = None
    if args.take:
        from .data import read_livelink_csv

        take = read_livelink_csv(_input(args.take, "--take"), clip=args.clip)
        poses = take.weights_for(rig.names, missing="zero")
        progress(f"read {args.take}: {take.n_frames} frames")
    try:
        report = autorig.check_rig(
            rig, poses, n_random=args.n_random, up=args.up, forward=args.forward,
            progress=progress,
        )  # fmt: skip
    except ValueError as error:
        raise CommandError(f"RIG {args.rig}: {error}") from None
    print(report.table())
    print(report.summary())
    if args.sheet:
        sheet = _output(args.sheet, (".png",))
        autorig.plot_check_frames(rig, report, sheet, title=f"{Path(args.rig).name}: "
                                  f"{report.summary()}")  # fmt: skip
        progress(f"wrote {sheet}: the worst frames")
    if args.json:
        from ._io import save_json

        save_json(_output(args.json, (".json",)), {"ok": report.ok, "checks": report.as_dict()})
    return 0 if report.ok else 1


def _add_check_parser(sub) -> None:
    about = (
        "A rigger's checks of an ARKit face rig: the blink covers the eye, the jaw opens the "
        "lips and moves the chin down, eyes and teeth move rigidly, shapes stay in their "
        "region, no flipped triangles or self-intersections under a take. Prints a table; "
        "exit status 1 when a hard check fails."
    )
    p = sub.add_parser("check", help=about, description=about)
    p.add_argument("rig", help="the rig: a .glb of canrig autorig, a .npz or an .fbx")
    p.add_argument("--take", metavar="CSV", help="a Live Link Face take to drive it with "
                   "(default: random sparse combinations of its own shapes)")  # fmt: skip
    p.add_argument("--head", metavar="HEAD", help="a mesh of the rig's neutral with its "
                   "triangles, for a rig file that has none")  # fmt: skip
    p.add_argument("--n-random", type=int, default=120, help="random poses without --take "
                   "(default: %(default)s)")  # fmt: skip
    p.add_argument("--up", default="+y", help="the rig's up axis (default: %(default)s)")
    p.add_argument("--forward", default="+z", help="the axis its face looks along "
                   "(default: %(default)s)")  # fmt: skip
    p.add_argument("--sheet", metavar="PNG", help="write a contact sheet of the worst frames")
    p.add_argument("--json", metavar="FILE", help="write the checks as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    _add_clip_option(p)
    p.set_defaults(run=_check)


def _is_avatar(path: Path) -> bool:
    """Whether ``path`` is a whole avatar for ``auto_rig_avatar``: a .vrm, a .glb or .fbx
    with a skeleton (a skin), or a .glb of a standing body."""
    from .autorig._avatar import standing_body
    from .data import load_fbx_scene
    from .rig import read_gltf_avatar

    suffix = path.suffix.lower()
    if suffix == ".vrm":
        return True
    try:  # a file neither reader takes is left to load_head, which says why
        if suffix == ".glb":
            avatar = read_gltf_avatar(path)
            return bool(avatar.document.get("skins")) or standing_body(avatar)
        if suffix == ".fbx":
            return any(m.skin is not None for m in load_fbx_scene(path).meshes)
    except (ValueError, OSError):
        return False
    return False


def _autorig_avatar(args, out: Path, progress) -> None:
    """``canrig autorig`` of a whole avatar: the same avatar with morph targets."""
    from . import autorig

    if out.suffix.lower() not in (".glb", ".vrm"):
        raise CommandError(f"-o {out}: an avatar is written as a .glb or .vrm")

    for option, given in (("--template", args.template), ("--examples", args.examples)):
        if given:
            raise CommandError(f"{option}: not with a whole avatar ({args.head}); pass the head")
    if args.units not in (None, "m"):
        raise CommandError(f"--units {args.units}: a glTF or converted FBX avatar is in metres")
    options = {"names": "source" if args.names == "ict" else "arkit"}
    if args.up is not None:
        options.update(up=args.up, forward=args.forward)
    method_class, model_path = _autorig_method_class(args)
    method = _autorig_method(args, method_class, model_path, None, progress)
    progress(f"reading the avatar {args.head}")
    try:
        result = autorig.auto_rig_avatar(
            args.head,
            out,
            method=method,
            replace=args.replace,
            extras=args.extras,
            check=not args.no_check,
            strict=args.strict,
            progress=progress,
            **options,
        )
    except autorig.OrientationError as error:
        raise CommandError(f"HEAD {args.head}: {str(error).replace('vertices: ', '', 1)}") from None
    except ValueError as error:
        if str(error).startswith("avatar: "):
            raise CommandError(f"HEAD {str(error)[len('avatar: ') :]}") from None
        raise
    progress(
        f"rigged {result.vertices_rigged} vertices of {list(result.head_meshes)} with "
        f"{len(result.names)} morph targets in {result.seconds['total']:.1f} s"
    )
    if result.checks is not None and not result.checks.ok:
        from .autorig._rig_checks import failed_hard_checks

        _warn(f"the face rig fails hard checks: {failed_hard_checks(result.checks)}")


# ---------------------------------------------------------------------------------- animate
def _key_times(take, name: str) -> np.ndarray:
    """(T,) seconds of a take's keys from its timecodes (dropped frames leave their gap);
    one frame apart, with a warning, when the timecodes repeat or go back."""
    times = (take.frame_number - take.frame_number[0]) / take.fps
    if take.n_frames > 1 and np.any(np.diff(times) <= 0):
        _warn(f"{name}: timecodes repeat or go back; keys placed one frame apart instead")
        times = np.arange(take.n_frames) / take.fps
    return times


def _animate(args) -> None:
    from ._io import save_npz
    from .data import read_livelink_csv
    from .rig import evaluate_batch, export_animated_gltf, validate_gltf

    out = _output(args.output, (".glb", ".usda", ".usdc", ".usd"))
    meshes_out = _output(args.meshes, (".npz",)) if args.meshes else None
    progress = _Progress(args.quiet)
    rig = _load_rig(args.rig)
    progress(f"read {args.rig}: {rig.n_blendshapes} blendshapes, {rig.n_vertices} vertices")
    take = read_livelink_csv(_input(args.take, "TAKE"), fps=args.fps, clip=args.clip)
    progress(
        f"read {args.take}: {take.n_frames} frames at {take.fps:g} fps "
        f"({'given' if args.fps else 'from the timecodes'}), {len(take.names)} channels, "
        f"rotations {list(take.rotation_names) or 'none'}"
    )
    weights = take.weights_for(rig.names, missing=args.missing)
    times = _key_times(take, args.take)
    head = None
    if args.head_rotation:
        have = [n for n in ("HeadYaw", "HeadPitch", "HeadRoll") if n in take.rotation_names]
        if len(have) == 3:
            index = [take.rotation_names.index(n) for n in have]
            head = take.head_eye_rotations[:, index] * args.rotation_scale
        else:
            _warn(f"{args.take}: no HeadYaw/HeadPitch/HeadRoll columns; no head rotation")
    progress(f"writing {out}: {take.n_frames} keys x {rig.n_blendshapes} morph targets")
    if out.suffix.lower() in (".usda", ".usdc", ".usd"):
        from .rig import export_usd

        export_usd(rig, out, weights=weights, fps=take.fps, times=times)
        progress(f"wrote {out}: UsdSkel blend shapes and a SkelAnimation (no head rotation)")
        args.validate = False  # the glTF validator reads glTF only
    else:
        export_animated_gltf(rig, weights, out, fps=take.fps, times=times, head_rotation=head)
        progress(f"wrote {out}")
    if meshes_out is not None:
        progress(f"evaluating the rig at {take.n_frames} frames")
        meshes = np.asarray(evaluate_batch(rig, weights, chunk=64), np.float32)
        save_npz(meshes_out, meshes=meshes, weights=weights, names=np.asarray(rig.names))
        progress(f"wrote {meshes_out}: the rig's meshes at every frame ({meshes.shape})")
    if args.validate:
        progress("running the Khronos glTF validator")
        report = validate_gltf(out)
        issues = report["issues"]
        progress(
            f"Khronos glTF validator: {issues['numErrors']} errors, "
            f"{issues['numWarnings']} warnings"
        )
        if issues["numErrors"]:
            raise CommandError(f"{out}: the glTF validator found {issues['numErrors']} errors")


# ----------------------------------------------------------------------------------- invert
def _read_meshes(path: Path, n_vertices: int, units: str) -> np.ndarray:
    from .data import load_head, read_arrays

    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() == ".obj")
        if not files:
            raise CommandError(f"MESHES {path}: the folder holds no .obj files")
        meshes = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # sizes are checked against the rig below
            for f in files:
                meshes.append(load_head(f, units=units).vertices)
    elif path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as z:
            key = next((k for k in ("meshes", "vertices") if k in z.files), None)
        if key is None:
            raise CommandError(f"MESHES {path}: expected an array 'meshes' (T, V, 3)")
        meshes = read_arrays(path, (key,))[key]
    else:
        raise CommandError(f"MESHES {path}: expected a folder of .obj files or an .npz")
    meshes = np.asarray(meshes, np.float32)
    if meshes.ndim != 3 or meshes.shape[1:] != (n_vertices, 3):
        raise CommandError(
            f"MESHES {path}: meshes of shape {meshes.shape[1:]}, the rig has ({n_vertices}, 3)"
        )
    if not np.all(np.isfinite(meshes)):
        raise CommandError(f"MESHES {path}: non-finite vertex positions")
    return meshes


def _read_points(path: Path) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """``--points FILE``: an .npz or .json with ``vertices`` (N,) vertex indices, or
    ``triangles`` (N,) and ``barycentric`` (N, 3) on the rig's faces."""
    import json

    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    elif path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise CommandError(f"--points {path}: not JSON ({error.msg})") from None
        if not isinstance(data, dict):
            raise CommandError(f"--points {path}: expected a JSON object")
    else:
        raise CommandError(f"--points {path}: expected an .npz or a .json file")
    if "vertices" in data:
        vertices = np.asarray(data["vertices"])
        if not np.issubdtype(vertices.dtype, np.integer):
            raise CommandError(f"--points {path}: 'vertices' must be integer vertex indices")
        return vertices
    if "triangles" in data and "barycentric" in data:
        triangles = np.asarray(data["triangles"])
        if not np.issubdtype(triangles.dtype, np.integer):
            raise CommandError(f"--points {path}: 'triangles' must be integer triangle indices")
        return triangles, np.asarray(data["barycentric"], np.float64)
    raise CommandError(
        f"--points {path}: expected 'vertices' (N,), or 'triangles' (N,) and 'barycentric' (N, 3)"
    )


def _invert(args) -> None:
    import jax
    from tqdm import tqdm

    from . import inverse
    from ._metrics import CM_TO_MM
    from .data import capture_from_weights, read_livelink_csv, write_livelink_csv
    from .rig import UNIT_IN_CM, evaluate_batch

    out = _output(args.output, (".csv",))
    progress = _Progress(args.quiet)
    rig = _load_rig(args.rig)
    progress(f"read {args.rig}: {rig.n_blendshapes} blendshapes, {rig.n_vertices} vertices")
    points = _read_points(_input(args.points, "--points")) if args.points else None
    problem = None
    if points is not None:
        try:
            problem = inverse.prepare(rig, points=points)
        except ValueError as error:
            raise CommandError(f"--points {args.points}: {error}") from None
        if args.meshes.lower().endswith(".obj") or Path(args.meshes).is_dir():
            raise CommandError(f"MESHES {args.meshes}: with --points, an .npz of point positions")
        progress(f"read {args.points}: {problem.n_vertices} points on the rig's surface")
    n_targets = rig.n_vertices if problem is None else problem.n_vertices
    meshes = _read_meshes(_input(args.meshes, "MESHES"), n_targets, rig.units)
    n_frames = meshes.shape[0]
    what = "points" if points is not None else "vertices"
    progress(f"read {n_frames} meshes of {meshes.shape[1]} {what}")
    timecodes = None
    if args.timecodes:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # its gaps are what is copied
            timecodes = read_livelink_csv(_input(args.timecodes, "--timecodes"), fps=args.fps)
        if timecodes.n_frames != n_frames:
            raise CommandError(
                f"--timecodes {args.timecodes}: {timecodes.n_frames} frames, MESHES "
                f"{args.meshes} {n_frames}; the timecodes are copied frame by frame"
            )
        steps = np.diff(timecodes.frame_number)
        progress(
            f"timecodes from {args.timecodes}: {n_frames} frames at {timecodes.fps:g} fps, "
            f"{int(np.maximum(steps - 1, 0).sum())} frames dropped in "
            f"{int((steps > 1).sum())} gaps (kept)"
        )
    expected = None
    if args.reference:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reference = read_livelink_csv(_input(args.reference, "--reference"))
            expected = reference.weights_for(rig.names, missing="zero")
        if expected.shape[0] != n_frames:
            raise CommandError(
                f"--reference {args.reference}: {expected.shape[0]} frames, MESHES "
                f"{args.meshes} {n_frames}"
            )
        if timecodes is None:
            progress(
                "note: the CSV's timecodes start at 00:00:00:00; --timecodes "
                f"{args.reference} would copy the reference take's"
            )
    cls = getattr(inverse, INVERSE_METHODS[args.method])
    fields = {f.name for f in dataclasses.fields(cls)}
    options = from_args(inverse.QuarticCD, args)
    method = cls(**{k: getattr(options, k) for k in fields if hasattr(options, k)})
    if problem is None:
        progress(f"preparing the inverse problem ({rig.n_blendshapes} blendshapes)")
        problem = inverse.prepare(rig)
    progress(f"solving {n_frames} frames with {method}")
    chunk = min(args.chunk, meshes.shape[0])
    solved = []
    for start in tqdm(range(0, meshes.shape[0], chunk), disable=args.quiet, desc="frames"):
        block = meshes[start : start + chunk]
        pad = chunk - block.shape[0]  # one compiled shape: the last block is padded
        block = np.concatenate([block, np.repeat(block[-1:], pad, axis=0)])
        solution = inverse.solve_sequence(problem, block, method, key=jax.random.key(start))
        solved.append(np.asarray(solution.weights)[: chunk - pad])
        watchdog.progress(f"frames {start}-{start + block.shape[0] - pad - 1}")
    weights = np.concatenate(solved)
    mixing, channels = _arkit_columns(rig)
    fps = None if timecodes is not None else (args.fps or 60)
    take = capture_from_weights(weights @ mixing, channels, fps=fps, timecodes=timecodes)
    write_livelink_csv(out, take)
    progress(f"wrote {out}: {weights.shape[0]} frames, {len(channels)} Live Link Face channels")
    # how well the solved weights reproduce the meshes: well posed even where the weights are
    # not (two nearly parallel blendshapes trade weight without changing the mesh)
    fitted = np.asarray(evaluate_batch(problem.rig, weights))  # at the points with --points
    mesh_mm = np.linalg.norm(fitted - meshes, axis=-1) * UNIT_IN_CM[rig.units] * CM_TO_MM
    print(
        f"mesh error of the solved weights over {meshes.shape[0]} frames x "
        f"{meshes.shape[1]} {what}: mean {mesh_mm.mean():.4f} mm, max {mesh_mm.max():.4f} mm"
    )
    if expected is not None:
        error = np.abs(weights - expected)
        print(
            f"weight error against {args.reference} over {weights.shape[0]} frames x "
            f"{weights.shape[1]} channels: mean {error.mean():.4f}, RMS "
            f"{np.sqrt((error**2).mean()):.4f}, max {error.max():.4f}"
        )


# --------------------------------------------------------------------------------- retarget
RETARGET_METHODS = {"newton": "QuarticNewton", **INVERSE_METHODS}
"""``--method`` values of ``canrig retarget`` (QuarticNewton first: it keeps the box and
converges in a few joint steps)."""


def _rig_with_every_shape(path: str, option: str, crop: str | None):
    """The rig of ``path``: an .fbx with every blend shape (``load_fbx_rig(names="all")``),
    else as ``_load_rig`` reads it."""
    from .rig import load_fbx_rig

    p = _input(path, option)
    if p.suffix.lower() == ".fbx":
        return load_fbx_rig(p, names="all", crop=crop)
    return _load_rig(path, option)


def _control_set(rig, control_set: str, option: str, path: str):
    """``rig`` cut to ``control_set`` (``all``: as it is)."""
    from .rig import select_control_set

    if control_set == "all":
        return rig
    try:
        return select_control_set(rig, control_set)
    except ValueError as error:
        message = str(error).replace("control_set: the rig", path, 1)
        raise CommandError(f"{option} {control_set}: {message}") from None


def _write_controls_csv(out: Path, take, weights: np.ndarray, names: Sequence[str]) -> None:
    """The Live Link Face layout (``Timecode``, ``BlendShapeCount``, one column per control,
    then the take's rotations) for controls of any name; ARKit ones through the app's writer."""
    from ._io import save_text
    from .data import capture_from_weights, format_timecode, write_livelink_csv
    from .rig import control_set_of

    rotations = np.asarray(take.head_eye_rotations, np.float32)
    if all(control_set_of(n) == "arkit" for n in names):
        capture = capture_from_weights(
            weights,
            names,
            timecodes=take,
            head_eye_rotations=rotations,
            rotation_names=take.rotation_names,
        )
        write_livelink_csv(out, capture)
        return
    header = ["Timecode", "BlendShapeCount", *names, *take.rotation_names]
    count = str(len(names) + len(take.rotation_names))
    sub_frame = np.zeros(take.n_frames) if take.sub_frame is None else take.sub_frame
    lines = [",".join(header)]
    for t in range(take.n_frames):
        stamp = format_timecode(int(take.frame_number[t]), float(sub_frame[t]), int(take.fps))
        values = np.concatenate([weights[t], rotations[t]]).astype(np.float32)
        cells = [np.format_float_positional(x, unique=True, trim="0") for x in values]
        lines.append(",".join([stamp, count, *cells]))
    save_text(out, "\n".join(lines) + "\n")


def _retarget(args) -> None:
    from . import inverse
    from ._metrics import CM_TO_MM
    from .data import read_livelink_csv
    from .rig import UNIT_IN_CM, control_set_of, evaluate_batch, export_animated_gltf

    out = _output(args.output, (".csv", ".glb"))
    progress = _Progress(args.quiet)
    crop = None if args.crop == "none" else args.crop
    full = _rig_with_every_shape(args.source, "--from", crop)
    source = _control_set(full, args.from_set, "--from-set", args.source)
    progress(
        f"read {args.source} ({args.from_set}): {source.n_blendshapes} controls, "
        f"{source.n_vertices} vertices"
    )
    target_path = args.target or args.source
    if args.target is not None and Path(args.target).resolve() != Path(args.source).resolve():
        full = _rig_with_every_shape(args.target, "--to", crop)
    target = _control_set(full, args.to_set, "--to-set", target_path)
    progress(f"read {target_path} ({args.to_set}): {target.n_blendshapes} controls")
    not_arkit = [n for n in source.names if control_set_of(n) != "arkit"]
    if not_arkit:
        raise CommandError(
            f"--from-set {args.from_set}: the take drives ARKit controls, and {len(not_arkit)} "
            f"of the source's have no ARKit name ({not_arkit[:5]}...); choose --from-set arkit"
        )
    take = read_livelink_csv(_input(args.take, "TAKE"), fps=args.fps, clip=args.clip)
    progress(f"read {args.take}: {take.n_frames} frames at {take.fps:g} fps")
    weights = take.weights_for(source.names, missing=args.missing)
    cls = getattr(inverse, RETARGET_METHODS[args.method])
    fields = {f.name for f in dataclasses.fields(cls)}
    if "alpha" not in fields and args.alpha != 0.0:
        _warn(f"--alpha: --method {args.method} takes no L1 weight; --alpha is not used")
    method = cls(**({"alpha": args.alpha} if "alpha" in fields else {}))
    progress(f"retargeting onto {target.n_blendshapes} controls with {method}")
    options = {"correctives": args.correctives, "warm_start": args.warm_start}
    try:
        solution = inverse.retarget(source, weights, target, method, **options)
    except ValueError as error:
        if str(error).startswith("target_rig"):
            raise CommandError(f"--to {target_path}: {error}") from None
        raise
    solved = np.asarray(solution.weights, np.float32)
    if out.suffix.lower() == ".csv":
        _write_controls_csv(out, take, solved, target.names)
    else:
        head = None
        have = [n for n in ("HeadYaw", "HeadPitch", "HeadRoll") if n in take.rotation_names]
        if args.head_rotation and len(have) == 3:
            head = take.head_eye_rotations[:, [take.rotation_names.index(n) for n in have]]
        times = _key_times(take, args.take)
        export_animated_gltf(target, solved, out, fps=take.fps, times=times, head_rotation=head)
    progress(f"wrote {out}: {take.n_frames} frames x {target.n_blendshapes} controls")
    # offsets from each rig's neutral, in mm: what retarget matches
    wanted = np.asarray(evaluate_batch(source, weights) - source.neutral)
    got = np.asarray(evaluate_batch(target, solved) - target.neutral)
    wanted, got = (x * UNIT_IN_CM[r.units] * CM_TO_MM for x, r in ((wanted, source), (got, target)))
    error_mm = np.linalg.norm(got - wanted, axis=-1)
    rmse = np.sqrt((error_mm**2).mean(axis=1))
    print(
        f"mesh error of the retargeted curves against the source over {take.n_frames} frames x "
        f"{target.n_vertices} vertices: per-frame RMSE mean {rmse.mean():.4f} mm, max "
        f"{rmse.max():.4f} mm; largest vertex error {error_mm.max():.4f} mm"
    )


# ---------------------------------------------------------------------------------- correct
def _correct(args) -> None:
    from . import wpse
    from .data import read_arrays, read_livelink_csv
    from .rig import BlendshapeRig, evaluate_batch, export_animated_gltf, export_gltf

    out = _output(args.output, (".glb",))
    progress = _Progress(args.quiet)
    rig = _load_rig(args.rig)
    progress(f"read {args.rig}: {rig.n_blendshapes} blendshapes, {rig.n_vertices} vertices")
    edits_path = _input(args.edits, "EDITS")
    data = read_arrays(edits_path, ("poses", "meshes"))
    poses, sculpted = np.asarray(data["poses"], np.float32), np.asarray(data["meshes"], np.float32)
    if poses.ndim != 2 or poses.shape[1] != rig.n_blendshapes:
        raise CommandError(
            f"EDITS {edits_path}: poses of shape {poses.shape}, expected (P, {rig.n_blendshapes})"
        )
    if sculpted.shape != (poses.shape[0], rig.n_vertices, 3):
        raise CommandError(
            f"EDITS {edits_path}: meshes of shape {sculpted.shape}, expected "
            f"({poses.shape[0]}, {rig.n_vertices}, 3)"
        )
    take = None
    if args.take:
        take = read_livelink_csv(_input(args.take, "--take"))
        frame_weights = take.weights_for(rig.names, missing="zero")
        progress(f"read {args.take}: {take.n_frames} frames at {take.fps:g} fps")
    else:
        frame_weights = poses
    edits = sculpted - np.asarray(evaluate_batch(rig, poses))
    progress(
        f"fitting WPSE on {poses.shape[0]} sculpted frames"
        + ("" if args.sigma is not None else " (leave-one-out width)")
    )
    prepared = wpse.prepare_edits(rig, poses, edits)
    sigma = args.sigma if args.sigma is not None else float(wpse.fit_sigma(prepared).sigma)
    model = wpse.fit_prepared(prepared, sigma)
    progress(f"fitted WPSE, sigma {sigma:.4g}; correcting {frame_weights.shape[0]} frames")
    posed = np.asarray(evaluate_batch(rig, frame_weights), np.float32)
    corrected = []
    for i, (w, p) in enumerate(zip(frame_weights, posed, strict=True)):
        corrected.append(np.asarray(wpse.apply(model, w, p)))
        watchdog.progress(f"frame {i}")
    corrections = np.stack(corrected) - posed
    # the correction baked: one morph target per frame, switched on at its own key only
    t = frame_weights.shape[0]
    baked = BlendshapeRig(
        rig.neutral,
        np.concatenate([np.asarray(rig.deltas), corrections]),
        rig.correctives,
        (*rig.names, *(f"wpse_frame_{i:04d}" for i in range(t))),
        rig.faces,
        units=rig.units,
    )
    progress(f"writing {out}: {baked.n_blendshapes} morph targets")
    if take is not None:
        weights = np.concatenate([frame_weights, np.eye(t, dtype=np.float32)], axis=1)
        times = _key_times(take, args.take)
        export_animated_gltf(baked, weights, out, fps=take.fps, times=times)
        where = f"animated over the {t} frames of {args.take}"
    else:
        export_gltf(baked, out)
        where = f"as {t} targets wpse_frame_i, one per sculpted pose (weight 1 at that pose)"
    print(
        "correction: BAKED (glTF morph targets are linear; WPSE's pose-space RBF cannot run in "
        f"a glTF player): {where}; max correction {np.abs(corrections).max():.4g} {rig.units}"
    )
    progress(f"wrote {out}")


# ------------------------------------------------------------------------------------- view
def _morph_option(text: str) -> tuple[str, float]:
    name, sep, value = text.rpartition("=")
    try:
        if not sep or not name:
            raise ValueError
        return name, float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected NAME=WEIGHT, got {text!r}") from None


def _size_option(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text!r}") from None
    if not (64 <= width <= 4096 and 64 <= height <= 4096):
        raise argparse.ArgumentTypeError(f"expected 64-4096 pixels a side, got {text!r}")
    return width, height


def _view(args) -> None:
    import signal
    import threading

    from . import viewer

    progress = _Progress(args.quiet)
    if args.screenshot:
        shot = viewer.screenshot_glb(
            _input(args.file, "FILE"),
            args.screenshot,
            time=args.time,
            morphs=dict(args.morph),
            wireframe=args.wireframe,
            face=args.face,
            size=args.size,
        )
        for level, text in shot.console:
            if level in ("error", "warning"):
                progress(f"page {level}: {text}")
        print(f"wrote {shot.path}: {Path(args.file).name} at {shot.time:.3f} s")
        if shot.errors:
            raise CommandError(f"FILE {args.file}: the page reported {len(shot.errors)} errors")
        return
    server = viewer.ViewerServer(_input(args.file, "FILE"), port=args.port)
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    server.start()
    try:
        print(server.summary.describe())
        print(f"serving on {server.url} (127.0.0.1 only); Ctrl-C stops", flush=True)
        if args.open:
            import webbrowser

            webbrowser.open(server.url)
        while not stop.wait(0.2):
            pass
    finally:
        server.stop()
        for s, handler in previous.items():
            signal.signal(s, handler)
    print("stopped", flush=True)


# ------------------------------------------------------------------------------------ main
def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``canrig`` parser; with ``command`` (a subcommand's name), only that subcommand's
    (so that ``canrig autorig`` does not import what ``canrig invert``'s options are read
    from)."""
    parser = _Parser(
        prog="canrig",
        description="From a head file and a phone capture to an animated rig (canrig_jax).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="SUBCOMMAND")
    for name, add in _SUBCOMMANDS.items():
        if command is None or name == command:
            add(sub)
    return parser


def _add_command(sub, name: str, help: str, inputs: Sequence[tuple[str, str]], out_help: str):
    """A subcommand's parser with its positional ``inputs``, ``--output`` and ``--quiet``."""
    p = sub.add_parser(name, help=help, description=help)
    for arg, text in inputs:
        p.add_argument(arg, help=text)
    p.add_argument("-o", "--output", required=True, help=out_help)
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    return p


def _add_autorig_parser(sub) -> None:
    p = _add_command(
        sub,
        "autorig",
        "Generate an ARKit blendshape rig (with correctives) for any neutral head.",
        [
            (
                "head",
                "head mesh (.obj, .ply, .gltf, .glb or .fbx), or a whole avatar (.glb or .fbx "
                "with a skeleton, .vrm 1.0): the avatar comes back with its face rigged",
            )
        ],
        "the rig, a .glb with named morph targets (centimetres); for an avatar, the same "
        "avatar with morph targets on its face meshes (.glb), or with VRM 1.0 expressions too "
        "(.vrm); a head's rig can also be written as UsdSkel blend shapes (.usda, .usdc, .usd)",
    )
    p.add_argument(
        "--method",
        choices=tuple(AUTORIG_METHODS),
        default=None,  # autorig.DEFAULT_METHOD (chosen on validation heads), or transfer
        help="raf: the RigAnyFace network; transfer: the template's expressions carried onto "
        "the head (anchored deformation transfer; closer without --examples on heads sculpted "
        "in another style); transfer-residual: transfer plus a learned residual "
        "(default: transfer)",
    )
    p.add_argument(
        "--template",
        metavar="RIG",
        help="carry this rig's shapes instead of ICT's (.glb, .npz or .fbx; cm, y up, facing +z)",
    )
    p.add_argument(
        "--examples",
        metavar="FILE",
        help="k of this head's ARKit shapes sculpted by its artist (.glb, .npz or .fbx on the "
        "head's mesh): the rig takes their amplitude and locality, and them as they are",
    )
    p.add_argument(
        "--names",
        choices=("arkit", "ict"),
        default="arkit",
        help="morph target names: ARKit's (browDownLeft) or the template's own (ict: ICT's "
        "browDown_L, or your --template's) (default: %(default)s)",
    )
    p.add_argument(
        "--up",
        help="the head's up axis, e.g. --up=+z (with --forward; default: found from the face)",
    )
    p.add_argument("--forward", help="the axis the face looks along, e.g. --forward=-y (with --up)")
    p.add_argument(
        "--units",
        choices=("mm", "cm", "dm", "m"),
        help="the head file's length unit (default: from the file or its size)",
    )
    p.add_argument(
        "--model",
        help="network checkpoint for --method raf or transfer-residual (default: the packaged "
        "model of that method)",
    )
    p.add_argument(
        "--extras",
        type=lambda text: [t.strip() for t in text.split(",") if t.strip()],
        metavar="SETS",
        help="add the targets apps expect, as documented sums of the ARKit shapes: visemes "
        "(the 15 Oculus visemes), rpm (Ready Player Me's mouthOpen, mouthSmile, eyesClosed, "
        "eyesLookUp, eyesLookDown), e.g. --extras visemes,rpm",
    )
    p.add_argument(
        "--strict",
        action="store_true",
        help="do not write a rig that fails a hard rig check (default: written, with a warning)",
    )
    p.add_argument("--no-check", action="store_true", help="skip the rig checks at the end")
    p.add_argument(
        "--replace",
        action="store_true",
        help="an avatar's face mesh that already has targets of these names gets them "
        "replaced (default: refused)",
    )
    p.set_defaults(run=_autorig)


def _add_clip_option(p) -> None:
    p.add_argument(
        "--clip",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="clip the take's weights to [0, 1] (a warning counts the cells outside either "
        "way; --no-clip keeps them as they are) (default: on)",
    )


def _add_animate_parser(sub) -> None:
    p = _add_command(
        sub,
        "animate",
        "Drive a rig with a Live Link Face CSV take: an animated glTF (morph weights over time).",
        [
            ("rig", "the rig: .glb from canrig autorig, a .npz or an .fbx rig"),
            ("take", "the .csv take"),
        ],
        "the animated .glb, or a .usda, .usdc or .usd (UsdSkel blend shapes and a "
        "SkelAnimation; needs usd-core)",
    )
    p.add_argument("--fps", type=int, help="the take's frame rate (default: from the timecodes)")
    p.add_argument(
        "--head-rotation",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="animate HeadYaw/HeadPitch/HeadRoll as the head's rotation (default: on)",
    )
    p.add_argument(
        "--rotation-scale",
        type=float,
        default=1.0,
        help="radians per unit of the take's rotation columns (default: %(default)s)",
    )
    p.add_argument(
        "--missing",
        choices=("zero", "raise"),
        default="zero",
        help="a rig channel the take lacks: weight 0 (named in a warning) or an error "
        "(default: zero)",
    )
    _add_clip_option(p)
    p.add_argument("--meshes", help="also write the rig's mesh at every frame to this .npz")
    p.add_argument(
        "--validate",
        action="store_true",
        help="run the Khronos glTF validator (needs node and npm gltf-validator)",
    )
    p.set_defaults(run=_animate)


def _add_invert_parser(sub) -> None:
    from .inverse import ORDERS, QuarticCD

    p = _add_command(
        sub,
        "invert",
        "Inverse rig: the weights of a mesh sequence, written as a Live Link Face CSV.",
        [
            ("rig", "the rig: .glb from canrig autorig, a .npz or an .fbx rig"),
            ("meshes", "a folder of .obj frames (sorted by name) or an .npz with 'meshes'"),
        ],
        "the .csv take",
    )
    p.add_argument(
        "--method",
        choices=tuple(INVERSE_METHODS),
        default="quartic",
        help="solver (default: %(default)s; quartic = Racković's coordinate descent)",
    )
    add_dataclass_options(
        p,
        QuarticCD,
        exclude=("trace", "newton", "upper"),
        choices={"order": ORDERS},
        help={
            "alpha": "L1 sparsity weight (methods that take it)",
            "passes": "coordinate-descent passes",
            "tol": "stop when a pass improves the objective by less",
            "order": "coordinate order",
        },
    )
    p.add_argument(
        "--fps",
        type=int,
        help="frame rate written (default: the --timecodes take's, else 60)",
    )
    p.add_argument("--chunk", type=int, default=32, help="frames per solve (default: 32)")
    p.add_argument(
        "--timecodes",
        metavar="TAKE.csv",
        help="copy this Live Link Face take's timecodes, gaps included (one per mesh; "
        "default: consecutive frames from 00:00:00:00)",
    )
    p.add_argument("--reference", help="a .csv take to report the weight error against")
    p.add_argument(
        "--points",
        metavar="FILE",
        help="solve from points of the surface (markers, landmarks): an .npz or .json with "
        "'vertices' (N,) vertex indices, or 'triangles' (N,) and 'barycentric' (N, 3) on the "
        "rig's faces; MESHES is then an .npz of (T, N, 3) point positions",
    )
    p.set_defaults(run=_invert)


def _add_retarget_parser(sub) -> None:
    from .rig import CONTROL_SETS

    p = _add_command(
        sub,
        "retarget",
        "Carry a Live Link Face take onto another set of controls of the same mesh (inverse "
        "rig through the mesh): e.g. ARKit -> SRanipal or FACS on a Rocketbox head.",
        [("take", "the .csv take (ARKit channels)")],
        "the target's curves: a .csv (Live Link Face layout, one column per target control) "
        "or an animated .glb of the target rig",
    )
    sets = (*CONTROL_SETS, "all")
    p.add_argument(
        "--from",
        dest="source",
        required=True,
        metavar="RIG",
        help="the rig the take drives: an .fbx (every blend shape is read), .glb or .npz",
    )
    p.add_argument(
        "--from-set",
        choices=sets,
        default="arkit",
        help="the source's controls, by name: the take's ARKit channels (default: %(default)s)",
    )
    p.add_argument("--to", dest="target", metavar="RIG", help="the target rig (default: --from)")
    p.add_argument(
        "--to-set",
        choices=sets,
        required=True,
        help="the target's controls: arkit (AK_NN_ / ARKit names), facs (AU_NN_), sranipal "
        "(SR_NN_), visemes (AA_VI_NN_), or all of the rig's shapes",
    )
    p.add_argument(
        "--crop",
        choices=("head", "none"),
        default="head",
        help="an .fbx body cut to the head, or kept whole (default: %(default)s)",
    )
    p.add_argument(
        "--method",
        choices=tuple(RETARGET_METHODS),
        default="newton",
        help="inverse-rig solver (default: %(default)s = QuarticNewton, projected Gauss-Newton)",
    )
    p.add_argument(
        "--alpha",
        type=float,
        default=0.0,
        help="L1 sparsity weight, squared target units (cm^2), for methods that take it "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--warm-start", action="store_true", help="start each frame from the previous one"
    )
    p.add_argument(
        "--correctives",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="invert on the target's correctives too (default: on)",
    )
    p.add_argument("--fps", type=int, help="the take's frame rate (default: from the timecodes)")
    p.add_argument(
        "--missing",
        choices=("zero", "raise"),
        default="zero",
        help="a source control the take lacks: weight 0 (named in a warning) or an error "
        "(default: zero)",
    )
    _add_clip_option(p)
    p.add_argument(
        "--head-rotation",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="a .glb output animates HeadYaw/HeadPitch/HeadRoll (default: on)",
    )
    p.set_defaults(run=_retarget)


def _add_correct_parser(sub) -> None:
    p = _add_command(
        sub,
        "correct",
        "WPSE: correct a rig from sculpted frames; the correction is baked into the glTF.",
        [
            ("rig", "the rig: .glb from canrig autorig, a .npz or an .fbx rig"),
            ("edits", "an .npz with 'poses' (P, K) rig weights and 'meshes' (P, V, 3) sculpts"),
        ],
        "the corrected .glb",
    )
    p.add_argument("--sigma", type=float, help="RBF width (default: leave-one-out fit)")
    p.add_argument("--take", help="bake the corrected rig over this .csv take (animated)")
    p.set_defaults(run=_correct)


def _add_view_parser(sub) -> None:
    about = "See a rig or a take: a local web viewer (127.0.0.1 only) for a .glb file."
    p = sub.add_parser("view", help=about, description=about)
    p.add_argument("file", metavar="FILE", help="the .glb (canrig autorig, animate or correct)")
    p.add_argument(
        "--port", type=int, default=8000, help="port on 127.0.0.1 (default: %(default)s; 0: any)"
    )
    p.add_argument("--open", action="store_true", help="open the page in the default browser")
    shot = p.add_argument_group("headless screenshot (needs Chromium)")
    shot.add_argument("--screenshot", metavar="OUT.png", help="render one frame and exit")
    shot.add_argument("--time", type=float, default=0.0, help="seconds into the take (default 0)")
    shot.add_argument(
        "--morph",
        type=_morph_option,
        action="append",
        default=[],
        metavar="NAME=WEIGHT",
        help="hold a morph target at a weight (repeatable)",
    )
    shot.add_argument("--wireframe", action="store_true", help="draw the wireframe")
    shot.add_argument("--face", action="store_true", help="frame what the morph targets move "
                      "(a whole avatar's face) instead of the whole model")  # fmt: skip
    shot.add_argument(
        "--size", type=_size_option, default=(960, 720), help="WIDTHxHEIGHT (default 960x720)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    p.set_defaults(run=_view)


# ----------------------------------------------------------------------------------- launch
def _launch(args) -> int:
    from . import distributed

    command = args.launched[1:] if args.launched[:1] == ["--"] else args.launched
    if not command:
        raise CommandError("COMMAND: give the command to run after --, e.g. -- canrig ...")
    if args.processes < 1:
        raise CommandError(f"--processes: expected at least 1, got {args.processes}")
    result = distributed.launch(command, args.processes, port=args.port, grace_s=args.grace)
    if not args.quiet or result.returncode:
        print(f"canrig launch: {result.describe()}", file=sys.stderr)
    return result.returncode


def _add_launch_parser(sub) -> None:
    about = (
        "Run N copies of a command on this machine as one multi-process JAX run "
        "(jax.distributed; on a cluster use srun or a Kubernetes indexed Job instead)."
    )
    p = sub.add_parser(
        "launch",
        help=about,
        description=about,
        usage="canrig launch [-h] [-n N] [--port PORT] [--grace S] [--quiet] -- COMMAND ...",
    )
    p.add_argument("-n", "--processes", type=int, default=2, help="processes (default: 2)")
    p.add_argument("--port", type=int, default=None, help="coordinator port (default: a free one)")
    p.add_argument(
        "--grace",
        type=float,
        default=60.0,
        help="seconds the others get to end by themselves after one fails, before they are "
        "stopped (default: %(default)s)",
    )
    p.add_argument("--quiet", action="store_true", help="no summary line when all succeed")
    p.add_argument("launched", nargs=argparse.REMAINDER, metavar="COMMAND")
    p.set_defaults(run=_launch)


XLA_CACHE_FOLDER = "xla"
"""The folder under the cache folder (``CANRIG_CACHE``) where the ``canrig`` console script
keeps its compiled XLA programs: a second run of a command compiles nothing it compiled
before (some 2-4 s of ``canrig autorig``)."""


_SUBCOMMANDS = {
    "autorig": _add_autorig_parser,
    "animate": _add_animate_parser,
    "invert": _add_invert_parser,
    "retarget": _add_retarget_parser,
    "correct": _add_correct_parser,
    "check": _add_check_parser,
    "view": _add_view_parser,
    "launch": _add_launch_parser,
}
"""Each subcommand's name and the function that adds its parser, in ``--help``'s order."""


def _keep_compiled_programs() -> None:
    """JAX's persistent compilation cache in ``cache_dir() / XLA_CACHE_FOLDER``, every program
    kept however fast it compiled; left as it is when the user set one
    (``JAX_COMPILATION_CACHE_DIR``)."""
    import jax

    from ._cache import cache_dir

    if jax.config.jax_compilation_cache_dir:
        return
    jax.config.update("jax_compilation_cache_dir", str(cache_dir() / XLA_CACHE_FOLDER))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``canrig`` console script; returns the exit status. Run as the
    script (``argv`` None: the process's own arguments) it keeps its compiled programs on
    disk (``_keep_compiled_programs``); called with ``argv`` from Python
    (``canrig_jax.run_command``) it leaves the caller's JAX configuration alone."""
    words = sys.argv[1:] if argv is None else list(argv)
    command = words[0] if words and words[0] in _SUBCOMMANDS else None
    args = build_parser(command).parse_args(argv)
    if argv is None:
        _keep_compiled_programs()
    with print_warnings("canrig"):
        try:
            status = watchdog.run_watched(args.run, f"canrig {args.command}", args)
        except (CommandError, ValueError, OSError, RuntimeError, ImportError) as error:
            print(f"canrig: error: {error}", file=sys.stderr)
            return 2
    return status if isinstance(status, int) else 0


if __name__ == "__main__":
    sys.exit(main())
