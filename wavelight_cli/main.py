"""`wavelight` command line: parse options, run the cached stages, print results.

Heavy modules (cv2, trimesh, h5py, embreex, OpenImageIO) are imported inside the stages, so
`wavelight --help` stays instant.
"""

from __future__ import annotations

import errno
import json
import os
import re
import sys
import tomllib
from dataclasses import replace
from pathlib import Path

import click

from pipelines.errors import InputError, OptionError
from pipelines.model.materials import MODELS
from pipelines.threads import configure_malloc

from .console import Console
from .help_text import SUMMARY, with_examples
from .scene import material_from_options, scene_folder

VIS_SECTION = "visibility"  # scene.toml section shared by every command that needs visibility


_OS_FIXES = {
    errno.ENOSPC: "free some disk space and rerun (earlier results and finished stages are kept)",
    errno.EDQUOT: "free some space within your quota and rerun (earlier results and finished stages are kept)",
    errno.EACCES: "check the permissions of the file and its folder",
    errno.EPERM: "check the permissions of the file and its folder",
    errno.EROFS: "copy the scene to a writable folder",
    errno.EISDIR: "a folder is where a file should be: move it away",
    errno.ENOTDIR: "a file is where a folder should be: move it away",
    errno.ENOENT: "check the path",
}


_NO_ERRNO_FIX = "check that the disk has free space and the folder is writable, then rerun (earlier results and " \
    "finished stages are kept)"


def os_error_line(exc: BaseException, scene: Path | None = None) -> str | None:
    """One error line for a failure of the file system (full disk, permissions, ...); None when
    `exc` is not one (that is a bug, and keeps its traceback). HDF5 reports a full disk as a
    RuntimeError naming errno 28, not as an OSError. An OSError without an errno (some libraries
    raise one with only a message, or none) is still a file-system failure: it gets a line too."""
    code = getattr(exc, "errno", None) if isinstance(exc, OSError) else None
    if code is None and "No space left on device" in str(exc):
        code = errno.ENOSPC
    if code is None and not isinstance(exc, OSError):
        return None
    where = getattr(exc, "filename", None) or scene or "."
    if isinstance(where, (str, Path)):  # (a temp file of an atomic write: the file the user knows)
        from pipelines.io.files import final_path

        where = final_path(where)
    in_the_way = None  # (a file, or a dangling link, where a folder must go: name it, not the path below it)
    if code == errno.ENOTDIR and isinstance(where, Path):
        in_the_way = next((p for p in where.parents if p.exists() and not p.is_dir()), None)
    elif code == errno.EEXIST and isinstance(where, Path) and where.is_symlink() and not where.exists():
        in_the_way = where
    if in_the_way is not None:
        kind = "a dangling symbolic link" if in_the_way.is_symlink() else "a file"
        return InputError(f"is {kind}, where wavelight writes a folder", in_the_way,
                          "move or delete it, then rerun").line()
    if code is not None:
        problem = getattr(exc, "strerror", None) or os.strerror(code)
        problem = problem[:1].lower() + problem[1:]  # "no space left on device"; a library's detail as it is
        fix = _OS_FIXES.get(code, "check the path and the disk, then rerun")
    else:
        problem = exc.strerror or (str(exc.args[0]) if exc.args else "") or "the operating system reported an error"
        fix = _NO_ERRNO_FIX
    lines = problem.strip().splitlines() or ["the operating system reported an error"]
    return InputError(lines[0], where, fix).line()


def one_line_usage_error(exc: click.UsageError) -> click.UsageError:
    """click's usage error as one line: click prints the usage and a hint above its `Error:` line
    when the error has a context; the hint goes on the line instead."""
    ctx, hint = exc.ctx, ""
    if ctx is not None and ctx.command.get_help_option(ctx) is not None:
        hint = f" Try '{ctx.command_path} {ctx.help_option_names[0]}' for help."
    one = click.UsageError(" ".join(exc.format_message().split()) + hint)  # no context: just the Error line
    one.exit_code = exc.exit_code
    return one


class WavelightGroup(click.Group):
    """Turns InputError and file-system failures into one `Error: ...` line and exit code 1 (no
    traceback); usage errors (click's, and OptionError: a bad option value or combination) into one
    line and exit code 2."""

    def make_context(self, info_name, args, parent=None, **extra):
        try:
            return super().make_context(info_name, args, parent, **extra)
        except click.exceptions.NoArgsIsHelpError:
            raise
        except click.UsageError as exc:  # the group's own options
            raise one_line_usage_error(exc) from None

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except click.exceptions.NoArgsIsHelpError:
            raise
        except click.UsageError as exc:  # an unknown command, a command's options
            raise one_line_usage_error(exc) from None
        except OptionError as exc:
            raise click.UsageError(exc.line()) from None
        except InputError as exc:
            raise click.ClickException(exc.line()) from None
        except (OSError, RuntimeError) as exc:
            line = os_error_line(exc, (ctx.obj or {}).get("scene"))
            if line is None:
                raise
            raise click.ClickException(line) from None
        except KeyboardInterrupt:
            click.echo("interrupted: the cache keeps finished work; rerun to continue", err=True)
            sys.exit(130)


class WavelightCommand(click.Command):
    """A subcommand: a bad option value that scene.toml set (not the command line) is an error in
    scene.toml, named as such (it said `--resolution must be ...` of an option the user never gave)."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except OptionError as exc:
            from click.core import ParameterSource

            # the options the problem names (whole names: --light is not --light-exposure), and where
            # each value came from; scene.toml is blamed only when it set every one of them
            named = [p for p in self.params if isinstance(p, click.Option)
                     and any(re.search(re.escape(o) + r"(?![\w-])", exc.problem) for o in p.opts if o.startswith("--"))]
            from_toml = [p for p in named if ctx.get_parameter_source(p.name) == ParameterSource.DEFAULT_MAP]
            scene = (ctx.obj or {}).get("scene")
            if not named or len(from_toml) < len(named) or scene is None:
                raise
            keys = ", ".join(p.opts[0].lstrip("-") for p in from_toml)
            raise InputError(f"{exc.problem} (set here: {keys})", Path(scene) / "scene.toml", exc.fix) from None


def _key_names(param: click.Parameter) -> list[str]:
    """scene.toml keys for an option: its long option names without dashes (`ray-backend`), and
    its Python name (`backend`), with - and _ alike."""
    names = [o.lstrip("-") for o in param.opts if o.startswith("--")]
    return names + [param.name]


def _param_for_key(cmd: click.Command, key: str) -> click.Parameter | None:
    norm = key.replace("_", "-")
    for p in cmd.params:
        if isinstance(p, click.Option) and norm in {n.replace("_", "-") for n in _key_names(p)}:
            return p
    return None


def _name(text: str) -> str:
    """A TOML section or key as the error line shows it (quoted names may hold line breaks)."""
    return text if text.replace("-", "").replace("_", "").isalnum() else repr(text)


def _value(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _load_scene_toml(ctx: click.Context, scene_dir: Path) -> dict:
    path = scene_dir / "scene.toml"
    if not path.exists():
        return {}
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid TOML ({exc})", path, "fix the syntax") from None
    except OSError as exc:
        raise InputError(f"cannot read it ({exc.strerror})", path, "make it a readable text file") from None
    group = ctx.command
    default_map: dict = {}
    for section, values in data.items():
        commands = [name for name, cmd in group.commands.items()
                    if name == section or (section == VIS_SECTION and getattr(cmd, "uses_visibility", False))]
        if not commands or not isinstance(values, dict):
            known = sorted(set(group.commands) | {VIS_SECTION})
            raise InputError(f"unknown section [{_name(section)}]", path, f"use one of: {', '.join(known)}")
        for key, value in values.items():
            for name in commands:
                cmd = group.commands[name]
                param = _param_for_key(cmd, key)
                if param is None:
                    if name == section:
                        options = sorted(_key_names(p)[0] for p in cmd.params if isinstance(p, click.Option))
                        raise InputError(f"unknown key {key!r} in [{_name(section)}]", path,
                                         f"valid keys: {', '.join(options)}")
                    continue
                if isinstance(param.type, click.Path) and isinstance(value, str) and value \
                        and not Path(value).is_absolute():
                    value = str(scene_dir / value)  # relative to the scene folder, not the working directory
                try:
                    with click.Context(cmd) as sub:
                        param.type_cast_value(sub, value)
                    if isinstance(param.type, click.Path) and value == "":
                        raise click.BadParameter("an empty path")
                except (click.BadParameter, TypeError, ValueError, AttributeError) as exc:
                    # click's types raise plain errors for a TOML value of the wrong kind (an array for a number)
                    why = exc.message if isinstance(exc, click.BadParameter) else f"not a valid {param.type.name}"
                    raise InputError(f"[{_name(section)}] {_name(key)} = {_value(value)}: {why}", path,
                                     "fix the value") from None
                default_map.setdefault(name, {})[param.name] = value
    return default_map


@click.group(cls=WavelightGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-s", "--scene", "scene_dir", default=".", show_default=True,
              type=click.Path(file_okay=False, path_type=Path), help="Scene folder (see README).")
@click.option("-q", "--quiet", is_flag=True, help="Only print errors and results.")
@click.option("--lock-wait", default=600.0, show_default=True, type=click.FloatRange(0),
              help="Seconds to wait for another run on the same scene.")
@click.version_option(package_name="wavelight")
@click.pass_context
def cli(ctx: click.Context, scene_dir: Path, quiet: bool, lock_wait: float):
    """Recover the light (and reflectance) of a scene from one calibrated photo of a known mesh.

    A scene is a folder (-s, README: Scene folder): the photo, the mesh, camera.json and pose.json
    (calibrate and register write them), optionally scene.toml with defaults per command. Each
    command is a cached stage: it runs again only when its inputs or options changed, and says
    why. Results go to the folder's out/. Try `wavelight COMMAND --help` for a command's options
    and examples, `make demo` for every stage on the sample scene.
    """
    configure_malloc()  # (one heap for the worker threads; freed arrays kept for the next: page faults)
    ctx.obj = {"scene": scene_dir, "console": Console(quiet), "lock_wait": lock_wait}
    if ctx.invoked_subcommand is not None and scene_dir.is_dir():
        try:
            ctx.default_map = _load_scene_toml(ctx, scene_dir)
        except InputError as exc:
            raise click.ClickException(exc.line()) from None


cli.help = with_examples(cli.help, "")

force_option = click.option("--force", is_flag=True, help="Rerun even if the cache is up to date.")


class Stops(click.ParamType):
    """A finite exposure in stops within +-MOST (2^100 ~ 1e30: any photo's range; beyond it the scale
    overflows or the PNG is all black or all white)."""

    name = "stops"
    MOST = 100.0

    def convert(self, value, param, ctx):
        try:
            v = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number of stops", param, ctx)
        if not (abs(v) <= self.MOST):  # (NaN fails too)
            self.fail(f"{value!r}: give a finite number of stops from {-self.MOST:g} to {self.MOST:g}", param, ctx)
        return v


exposure_option = click.option("--exposure", type=Stops(), default=None,
                               help="PNG exposure in stops [default: the photo's, its 99.5th-percentile "
                                    "radiance white: a darker light looks darker]. Only redraws the PNG.")


DEFAULT_R = 32  # = pipelines.controllers.visibility.DEFAULT_RESOLUTION (not imported: --help stays instant)
R_HELP = ("Cube-map face resolution R (power of two): 3R^2 light directions with --hemisphere, 6R^2 with "
          "--sphere.")


def visibility_options(f=None, *, resolution_default: int | None = DEFAULT_R, default_note: str | None = None):
    """Options of the visibility stage, shared by every command that needs it. A command whose R
    and hemisphere come from elsewhere when not given (relight: the solve's) passes
    resolution_default=None and says so in `default_note` (shown as the options' default)."""
    if f is None:
        return lambda g: visibility_options(g, resolution_default=resolution_default, default_note=default_note)
    given = resolution_default is not None
    opts = [
        click.option("--resolution", "-R", default=resolution_default, show_default=given, type=int,
                     help=R_HELP + ("" if given else f" [default: {default_note}]")),
        click.option("--hemisphere/--sphere", default=True if given else None, show_default=given,
                     help="Upper hemisphere only (the paper) or the full sphere of light."
                          + ("" if given else f" [default: {default_note}]")),
        click.option("--supersample", default=1, show_default=True, type=int,
                     help="k x k shadow rays per texel (fractional visibility; 1 = texel centre only)."),
        click.option("--edge-margin", default=1, show_default=True, type=int,
                     help="Pixels to drop around silhouettes and depth jumps (mixed pixels)."),
        click.option("--ray-backend", "backend", default="embree", show_default=True,
                     type=click.Choice(["embree", "reference"]), help="Ray caster (reference is slow, for tests)."),
        click.option("--visibility", "visibility_method", default="adaptive", show_default=True,
                     type=click.Choice(["adaptive", "exact"]),
                     help="adaptive: cast shadow rays where the image shows the shadows change and infer the rest "
                          "from neighbouring pixels (the check's error rate is reported); exact: every ray."),
    ]
    for opt in reversed(opts):
        f = opt(f)
    f.uses_visibility = True
    return f


def _vis_opts(kw):
    from pipelines.controllers.visibility import VisibilityOptions

    return VisibilityOptions(kw.pop("resolution"), kw.pop("hemisphere"), kw.pop("supersample"), kw.pop("edge_margin"),
                             kw.pop("backend"), kw.pop("visibility_method"))


def views_options(f):
    """Which of the scene's photos a command uses (README: Scene folder, views/NAME/)."""
    opts = [
        click.option("--views", "views", default=None, metavar="NAMES",
                     help="Comma-separated photos to use: main (the scene folder's own photo) and the names of "
                          "folders under views/ [default: all of them]."),
        click.option("--single-view", is_flag=True, help="Use the main photo only (= --views main)."),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


def _views(kw) -> str | None:
    views, single = kw.pop("views"), kw.pop("single_view")
    if single and views not in (None, "main"):
        raise OptionError(f"--single-view and --views {views} contradict each other", None, "pass one of them")
    return "main" if single else views


def _command(name, **kwargs):
    """A subcommand: its summary in the group's list (help_text.SUMMARY), its docstring and
    examples (help_text.EXAMPLES) as its help."""
    def deco(f):
        cmd = cli.command(name, cls=WavelightCommand, short_help=SUMMARY[name], **kwargs)(f)
        cmd.help = with_examples(cmd.help, name)
        cmd.uses_visibility = getattr(f, "uses_visibility", False)
        return cmd
    return deco


@_command("calibrate")
@click.option("--images", default=None,
              help="Photos of the target: a glob relative to the scene folder (default: every photo in calib/).")
@click.option("--pattern", default="acircles", show_default=True,
              type=click.Choice(["acircles", "circles", "chessboard", "charuco"]),
              help="Target: OpenCV's asymmetric circle grid (the paper's dots), a symmetric circle grid, a "
                   "chessboard, or a ChArUco board (a chessboard with ArUco markers: partly hidden views count).")
@click.option("--pattern-size", default="4x11", show_default=True,
              help="COLSxROWS as OpenCV counts them: dots per row x rows (circle grids), inner corners (chessboard), "
                   "squares (charuco).")
@click.option("--spacing", default=None,
              help="Dot or square spacing with a unit (20mm, 2cm, 0.02m, 1in; a bare number is mm). acircles: half "
                   "the distance of two dots in a row (OpenCV's convention). The intrinsics do not depend on it.")
@click.option("--marker-size", default=None, help="charuco: the ArUco marker's side with a unit (e.g. 22mm).")
@click.option("--dictionary", default="DICT_5X5_100", show_default=True,
              help="charuco: OpenCV's predefined ArUco dictionary of the board (DICT_4X4_50 ... DICT_7X7_1000).")
@click.option("--fix-k3", is_flag=True, help="Fix the 6th-order radial term k3 at 0 (lenses with little distortion).")
@click.option("--zero-tangent", is_flag=True, help="Fix the tangential distortion p1, p2 at 0.")
@click.option("--fix-aspect", is_flag=True, help="Fix fx/fy (square pixels).")
@click.option("--outlier-factor", default=5.0, show_default=True, type=float,
              help="Drop a photo whose reprojection RMS exceeds this many times the median photo's (and 2 px), "
                   "then calibrate again.")
@click.option("--force", is_flag=True, help="Rerun even if up to date; replace a hand-written camera.json.")
@click.pass_obj
def calibrate_cmd(obj, images, pattern, pattern_size, spacing, marker_size, dictionary, fix_k3, zero_tangent,
                  fix_aspect, outlier_factor, force):
    """Camera intrinsics and lens distortion from photos of a target -> camera.json, out/calibrate/*_overlay.png."""
    from pipelines.controllers.calibrate import CalibrateOptions

    from .stages.calibrate import calibrate_stage

    scene = scene_folder(obj["scene"])
    opts = CalibrateOptions(images, pattern, pattern_size, spacing, marker_size, dictionary, fix_k3, zero_tangent,
                            fix_aspect, outlier_factor)
    calibrate_stage(scene, opts, obj["console"], force, obj["lock_wait"])


@_command("register")
@click.option("--method", default="sqpnp", show_default=True, type=click.Choice(["sqpnp", "iterative"]),
              help="solvePnP solver for the start (SQPnP is global; iterative is OpenCV's DLT/homography + LM); "
                   "Levenberg-Marquardt refines either.")
@click.option("--ransac", default="auto", show_default=True, type=click.Choice(["auto", "on", "off"]),
              help="RANSAC against wrong clicks: auto = when a residual exceeds --outlier-threshold.")
@click.option("--outlier-threshold", type=float, default=None,
              help="Residual (px) above which a point is an outlier [default: 0.5 % of the image diagonal, >= 3 px].")
@click.option("--max-rms", type=float, default=None,
              help="Fail when the inliers' RMS exceeds this (px) [default: half the outlier threshold].")
@click.option("--max-mesh-distance", type=float, default=0.01, show_default=True,
              help="Warn about 3D points farther than this fraction of the mesh's size from its surface.")
@click.option("--edge-refine/--no-edge-refine", default=True, show_default=True,
              help="Refine the pose so that the mesh's outline falls on the photo's edges, the clicks held within "
                   "their noise (kept only if the outline fits the edges better and the clicks' RMS stays under "
                   "--max-rms).")
@click.option("--force", is_flag=True, help="Rerun even if up to date; replace a hand-written pose.json.")
@views_options
@click.pass_obj
def register_cmd(obj, method, ransac, outlier_threshold, max_rms, max_mesh_distance, edge_refine, force, **kw):
    """The mesh's pose from 2D-3D correspondences (correspondences.csv + camera.json) -> pose.json,
    out/register_overlay.png; each views/NAME/ with a correspondences.csv likewise -> its pose.json,
    out/views/NAME/register_overlay.png."""
    from pipelines.controllers.register import RegisterOptions

    from .stages.register import register_views

    scene = scene_folder(obj["scene"])
    opts = RegisterOptions(method, ransac, outlier_threshold, max_rms, max_mesh_distance, edge_refine)
    register_views(scene, opts, obj["console"], force, obj["lock_wait"], _views(kw))


@_command("visibility")
@visibility_options
@force_option
@views_options
@click.pass_obj
def visibility_cmd(obj, force, **kw):
    """Ray-cast the shadow of every light direction at every used pixel of each photo (cached per
    photo, resumable)."""
    from .scene import scene_views
    from .stages.visibility import visibility_stage

    scene = scene_folder(obj["scene"])
    select = _views(kw)
    opts = _vis_opts(kw)
    for view in scene_views(scene, select):
        visibility_stage(scene, opts, obj["console"], force, obj["lock_wait"], view)


MATERIAL_JSON = ("Material JSON ({'model': 'blinn-phong', 'kd': [..], 'ks': [..], 'n': 30}, or {'model': 'plastic', "
                 "'kd': [..], 'alpha': 0.1, 'distribution': 'ggx', 'ior': 1.49})")
PLASTIC_HELP = {  # --alpha, --ior, --distribution: the `plastic` model's own parameters (README: The reflectance fit)
    "alpha": "plastic: microfacet roughness alpha, 0 = smooth (Mitsuba's alpha) [default: 0.1]",
    "ior": "plastic: the coating's index of refraction [default: 1.49]",
    "distribution": "plastic: microfacet distribution [default: ggx]",
}
MATERIAL_HELP = {  # option -> help, per meaning of the material options
    "given": {  # render: the material rendered
        "material_file": f"{MATERIAL_JSON}; the options below override its fields.",
        "model": "Reflectance model [default: the file's, else lambert].",
        "kd": "Diffuse albedo RGB [default: 1 1 1: the light holds the albedo, README: Conventions].",
        "ks": "Specular RGB [default: 0 0 0].",
        "shininess": "Specular exponent n [default: 1].",
    },
    "solve": {  # solve: the material of the light solve, or the reflectance fit's start
        "material_file": f"{MATERIAL_JSON}: the material the light is solved under (implies --reflectance given).",
        "model": "Reflectance model of the material (implies --reflectance given; see --reflectance).",
        "kd": "Diffuse albedo RGB: sets the light's scale [default: 1 1 1: the light holds the albedo, README: "
              "Conventions].",
        "ks": "Specular RGB; with a fitted reflectance (--reflectance auto or a model name) the fit's start "
              "[default: 0 0 0; the fit starts at 0.25 x kd].",
        "shininess": "Specular exponent n; with a fitted reflectance the fit's start [default: 1; the fit starts at "
                     "20].",
    },
    "fitted": {  # compare, relight, insert: the scene's material, by default the one solve fitted
        "material_file": f"{MATERIAL_JSON} instead of the reflectance solve fitted (out/reflectance.json). Any "
                         "material option replaces the fitted material as a whole: fields not given are kd 1 1 1, "
                         "ks 0 0 0, n 1, lambert.",
        "model": "Reflectance model [default: the fitted one (out/reflectance.json)].",
        "kd": "Diffuse albedo RGB [default: the fitted kd (out/reflectance.json)].",
        "ks": "Specular RGB [default: the fitted ks (out/reflectance.json)].",
        "shininess": "Specular exponent n [default: the fitted n (out/reflectance.json)].",
    },
}


def material_options(role: str):
    """Reflectance options (--material, --model, --kd, --ks, --shininess) with the help of their
    meaning in a command: 'given' (render), 'solve', 'fitted' (compare, relight, insert)."""
    text = MATERIAL_HELP[role]

    def deco(f):
        opts = [
            click.option("--material", "material_file", type=click.Path(dir_okay=False, path_type=Path),
                         help=text["material_file"]),
            click.option("--model", type=click.Choice(list(MODELS)), help=text["model"]),
            click.option("--kd", type=(float, float, float), default=None, help=text["kd"]),
            click.option("--ks", type=(float, float, float), default=None, help=text["ks"]),
            click.option("--shininess", type=click.FloatRange(0), default=None, help=text["shininess"]),
            click.option("--alpha", type=click.FloatRange(0, 4), default=None,
                         help=PLASTIC_HELP["alpha"] + ("; with a fitted reflectance the fit's start" if role == "solve"
                                                       else "") + "."),
            click.option("--ior", type=click.FloatRange(1.05, 3.0), default=None,
                         help=PLASTIC_HELP["ior"] + ("; a fit keeps it" if role == "solve" else "") + "."),
            click.option("--distribution", type=click.Choice(["ggx", "beckmann"]), default=None,
                         help=PLASTIC_HELP["distribution"] + "."),
        ]
        for opt in reversed(opts):
            f = opt(f)
        return f
    return deco


def _material(kw, given: set | None = None):
    return material_from_options(kw.pop("material_file"), kw.pop("model"), kw.pop("kd"), kw.pop("ks"),
                                 kw.pop("shininess"), given, kw.pop("alpha"), kw.pop("ior"), kw.pop("distribution"))


def _material_or_fitted(kw, scene):
    """The material options if any is given, else the reflectance `solve` fitted
    (out/reflectance.json) when there is one, else the defaults. Returns (material, the file used)."""
    given: set = set()
    material = _material(kw, given)
    fitted = scene.out / "reflectance.json"
    if not given and fitted.is_file():
        return material_from_options(fitted, None, None, None, None), fitted
    return material, None


@_command("render")
@click.option("--light", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Lat-long light (EXR/HDR; docs/DESIGN.md §2: H x 2H, row 0 = the zenith, +Z up).")
@material_options("given")
@exposure_option
@visibility_options
@force_option
@click.pass_obj
def render_cmd(obj, light, exposure, force, **kw):
    """Render the input view under a given light and material -> out/render.exr, out/render.png."""
    from .stages.render import render_stage

    scene = scene_folder(obj["scene"])
    material = _material(kw)
    render_stage(scene, _vis_opts(kw), light, material, exposure, obj["console"], force, obj["lock_wait"])


def solve_options(f):
    """Options of the light solve, shared by solve and compare."""
    opts = [
        click.option("--levels", default="auto", show_default=True,
                     help="Refinement levels (wavelet, quadtree) or number of lights (points): 'auto' stops "
                          "when the held-out error stops improving; a number fixes it."),
        click.option("--face-resolution", type=int, default=None,
                     help="discrete: face resolution of the texel grid (power of two <= --resolution; "
                          "default --resolution)."),
        click.option("--sh-order", type=int, default=2, show_default=True,
                     help="sh: highest order l ((l+1)^2 coefficients)."),
        click.option("--held-out", type=float, default=0.1, show_default=True,
                     help="Fraction of the pixels kept out of the fit to choose the model size."),
        click.option("--min-gain", type=float, default=0.01, show_default=True,
                     help="--levels auto: a level must lower the held-out error by this fraction to be kept."),
        click.option("--linear-input", is_flag=True,
                     help="The photo's 8/16-bit values are linear, not sRGB."),
        click.option("--exact", is_flag=True,
                     help="The reference route: every shadow ray (--visibility exact) and dense normal equations "
                          "over every used pixel, instead of a weighted sample of them (slow; for checking)."),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


def _solve_opts(kw, basis="wavelet", sh_nonnegative=False):
    from pipelines.controllers.solve import SolveOptions
    from pipelines.light.bases import LightOptions

    light = LightOptions(basis, str(kw.pop("levels")), kw.pop("min_gain"), kw.pop("face_resolution"), kw.pop("sh_order"),
                         sh_nonnegative)
    return SolveOptions(light, kw.pop("held_out"), kw.pop("linear_input"), kw.pop("exact"))


def reflectance_options(f):
    """How solve treats the reflectance."""
    opts = [
        click.option("--reflectance", type=click.Choice(["auto", "lambert", "blinn-phong", "phong", "phong-classic",
                                                         "plastic", "given"]), default=None,
                     help="Fit the reflectance: 'auto' (default) keeps Lambertian unless a Blinn-Phong term lowers "
                          "the held-out error by --min-specular-gain; a model name fits that model (ks, n, kd "
                          "colour) by Levenberg-Marquardt, alternating with the light; 'given' uses the material "
                          "options as they are (the default when --material or --model is given)."),
        click.option("--max-rounds", type=int, default=8, show_default=True,
                     help="Most light/reflectance rounds of the alternation (it stops earlier when a round "
                          "lowers the error by < 0.1 %)."),
        click.option("--min-specular-gain", type=float, default=0.05, show_default=True,
                     help="--reflectance auto: the held-out error must drop by this fraction to keep a "
                          "specular term."),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


@_command("solve")
@click.option("--basis", default="wavelet", show_default=True,
              type=click.Choice(["wavelet", "quadtree", "discrete", "sh", "points"]),
              help="Light representation: the paper's adaptive Haar wavelets, its quadtree twin, one value per "
                   "texel, spherical harmonics, or a few directional lights.")
@click.option("--sh-nonnegative", is_flag=True, help="sh: constrain the light to be >= 0 at every texel.")
@click.option("--single-material", is_flag=True,
              help="Ignore the mesh's parts (OBJ usemtl groups, glTF materials, materials.toml) and textures: one "
                   "uniform material for the whole scene.")
@click.option("--no-texture", is_flag=True,
              help="Ignore the parts' textures (map_Kd, baseColorTexture) and vertex colours: each part is one "
                   "fitted colour.")
@click.option("--texture-colour", is_flag=True,
              help="Fit an RGB colour per part on top of its texture (default: one grey scale per textured part).")
@click.option("--shared-ks", is_flag=True,
              help="The glossy parts share the material's one ks (default: each glossy part gets its own where its "
                   "pixels show its highlight: reflectance.json's parts[].ks).")
@click.option("--robust/--no-robust", default=True, show_default=True,
              help="Down-weight the few pixels the model cannot explain (a dust speck, a mis-registered rim, a "
                   "highlight no lobe fits: at most 5 %, beyond 4 noise scales) and solve again (auto choosing "
                   "its model again); "
                   "solve_report.json's 'robust' says how many.")
@click.option("--clipped", type=click.Choice(["bound", "drop"]), default="bound", show_default=True,
              help="Clipped (saturated) pixels of 8/16-bit photos: lower bounds of the light's prediction "
                   "(fitted in the robust pass), or left out.")
@click.option("--view-exposure", type=click.Choice(["fit", "same"]), default="fit", show_default=True,
              help="Several photos (views/): fit one gain per photo relative to the main one (auto exposure, "
                   "solve_report.json's views give each), or take them to be of one exposure (fixed settings).")
@solve_options
@reflectance_options
@material_options("solve")
@exposure_option
@visibility_options
@force_option
@views_options
@click.pass_obj
def solve_cmd(obj, basis, sh_nonnegative, single_material, no_texture, texture_colour, shared_ks, robust, clipped,
              view_exposure, reflectance, max_rounds, min_specular_gain, exposure, force, **kw):
    """Recover the light (and reflectance) from the photo -> out/light_latlong.exr, relit.png,
    reflectance.json, solve_report.json, ..."""
    from pipelines.controllers.solve import ReflectanceOptions
    from pipelines.model.parts import PartsOptions

    from .stages import solve

    scene = scene_folder(obj["scene"])
    select = _views(kw)
    given: set = set()
    material = _material(kw, given)
    if reflectance is None:
        reflectance = "given" if given & {"file", "model"} else "auto"
    refl = ReflectanceOptions(reflectance, max_rounds, min_specular_gain)
    opts = replace(_solve_opts(kw, basis, sh_nonnegative), robust=robust, clipped=clipped, view_exposure=view_exposure)
    solve.solve_stage(scene, _vis_opts(kw), opts, material, exposure, obj["console"], force, obj["lock_wait"],
                      refl, given, select, PartsOptions(not single_material, not no_texture, texture_colour,
                                                                   shared_ks))


@_command("compare")
@solve_options
@material_options("fitted")
@visibility_options
@force_option
@click.pass_obj
def compare_cmd(obj, force, **kw):
    """Solve with every basis on this scene -> out/compare.md (table), compare.json, compare.png (speed vs error).

    The material is the reflectance fitted by `solve` (out/reflectance.json) unless material options are given."""
    from pipelines.controllers.solve import material_text

    from .stages import solve

    scene = scene_folder(obj["scene"])
    material, fitted = _material_or_fitted(kw, scene)
    if fitted is not None:
        obj["console"].say(f"compare: material from {fitted.name} (fitted by solve): {material_text(material)}")
    opts = replace(_solve_opts(kw), robust=False, clipped="drop")  # (compare: the bases on the plain fit)
    solve.compare_stage(scene, _vis_opts(kw), opts, material, obj["console"], force, obj["lock_wait"])


@_command("relight")
@click.option("--light", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A lat-long light (EXR/HDR; docs/DESIGN.md §2: H x 2H, row 0 = the zenith, +Z up) "
                   "[default: the light solve recovered].")
@click.option("--rotate", type=float, default=0.0, show_default=True,
              help="Turn the light about +Z by this many degrees (azimuth phi -> phi + DEG).")
@click.option("--light-exposure", type=Stops(), default=0.0, show_default=True,
              help="Scale the light by 2^STOPS (the PNG keeps the photo's exposure: -1 looks one stop "
                   "darker).")
@click.option("--view", "view_pose", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Render from another view: one of the scene's photos by its name (a folder under views/, or "
                   "main), with its own camera, pose and photo, which the render is compared with; or any "
                   "other view's pose.json (visibility for it is computed once and cached).")
@click.option("--view-camera", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The other view's camera.json [default: the scene's].")
@click.option("--reference", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="An image to compare with [default: the view's photo, when the view is one of the scene's "
                   "photos and the light is the recovered one].")
@click.option("--reference-mask", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Where to compare (white = compare) [default: every rendered pixel].")
@click.option("--name", default="relight", show_default=True,
              help="Output names: out/NAME.exr, NAME.png, NAME_residual.png, NAME.json.")
@material_options("fitted")
@exposure_option
@visibility_options(resolution_default=None, default_note="the solve's, with the recovered light; "
                    f"{DEFAULT_R} and the hemisphere with --light")
@force_option
@click.pass_context
def relight_cmd(ctx, light, rotate, light_exposure, view_pose, view_camera, reference, reference_mask, name, exposure,
                force, **kw):
    """Render the scene under the recovered light (or any lat-long light, turned and scaled), from the
    photo's view or another one, with the fitted reflectance -> out/NAME.exr/png and its error."""
    from .stages.relight import RelightOptions, relight_stage

    obj = ctx.obj
    scene = scene_folder(obj["scene"])
    material, material_path = _material_or_fitted(kw, scene)
    solved_cube = None
    if light is None and (kw["resolution"] is None or kw["hemisphere"] is None) \
            and (scene.out / "coefficients.h5").is_file():
        from .scene import solved_light

        solved_cube = solved_light(scene)[1]
    if kw["resolution"] is None:  # not given (command line or scene.toml): the solve's R, else the default
        kw["resolution"] = solved_cube.resolution if solved_cube is not None else DEFAULT_R
    if kw["hemisphere"] is None:
        kw["hemisphere"] = solved_cube.hemisphere if solved_cube is not None else True
    opts = RelightOptions(light, rotate, light_exposure, view_pose, view_camera, reference, reference_mask, exposure,
                          name)
    relight_stage(scene, _vis_opts(kw), opts, material, material_path, obj["console"], force, obj["lock_wait"])


@_command("insert")
@click.option("--object", "object_arg", default="sphere", show_default=True,
              help="The virtual object: a mesh file (its own coordinates, +Z up) or 'sphere'.")
@click.option("--at", type=(float, float, float), required=True,
              help="Where the object's origin goes, world coordinates (a sphere's centre).")
@click.option("--scale", type=float, default=1.0, show_default=True, help="Scale the object about its origin.")
@click.option("--rotate-z", type=float, default=0.0, show_default=True, help="Turn the object about +Z (degrees).")
@click.option("--radius", type=float, default=None, help="sphere: radius [default: 10 % of the scene's size].")
@click.option("--object-material", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The object's material JSON (same format as --material).")
@click.option("--object-kd", type=(float, float, float), default=None,
              help="The object's diffuse albedo, relative to the scene's kd (the light holds the scene's albedo "
                   "when kd = 1) [default: 0.8 0.8 0.8].")
@click.option("--light", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A lat-long light [default: the light solve recovered].")
@click.option("--resolution", "-R", type=int, default=None,
              help="Cube-map R of the light [default: the solve's, or 32 for --light].")
@click.option("--supersample", type=int, default=1, show_default=True, help="k x k shadow rays per texel.")
@click.option("--visibility", "visibility_method", default="adaptive", show_default=True,
              type=click.Choice(["adaptive", "exact"]),
              help="The scene's cached visibility to reuse (the object's own shadow rays are always cast).")
@click.option("--view", "view_name", default=None,
              help="Insert into another of the scene's photos: its name (a folder under views/, or main) "
                   "[default: the scene folder's photo].")
@click.option("--name", default="insert", show_default=True, help="Output names: out/NAME.exr/png, NAME_render.exr, "
              "NAME_shadow.png, NAME.json.")
@material_options("fitted")
@exposure_option
@force_option
@click.pass_obj
def insert_cmd(obj, **kw):
    """Put a virtual object into the photo: shaded by the recovered light with its own shadows, its
    shadow on the known geometry added by differential rendering -> out/NAME.exr/png."""
    from .stages.insert import InsertOptions, insert_stage

    scene = scene_folder(obj["scene"])
    material, material_path = _material_or_fitted(kw, scene)
    opts = InsertOptions(kw.pop("object_arg"), kw.pop("at"), kw.pop("scale"), kw.pop("rotate_z"), kw.pop("radius"),
                         kw.pop("object_material"), kw.pop("object_kd"), kw.pop("light"), kw.pop("resolution"),
                         kw.pop("supersample"), kw.pop("exposure"), kw.pop("name"), kw.pop("view_name"))
    insert_stage(scene, opts, material, material_path, obj["console"], kw.pop("force"), obj["lock_wait"],
                 kw.pop("visibility_method"))


@_command("export")
@click.option("--format", "formats", multiple=True, type=click.Choice(["mitsuba", "blender", "opengl", "all"]),
              default=("all",), show_default=True,
              help="Mitsuba 3 envmap (EXR + emitter XML), Blender world (equirectangular EXR), OpenGL / three.js "
                   "cube faces (px nx py ny pz nz EXR); repeat the option for several.")
@click.option("--light", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A lat-long light to convert [default: the light solve recovered].")
@click.option("--height", type=int, default=None,
              help="Rows of the lat-long exports of the recovered light [default: 4 x the solve's R, at least "
                   "64]; a --light file keeps its own rows.")
@click.option("--face-size", type=int, default=None,
              help="Cube face size of the OpenGL faces [default: the solve's R; 64 with --light].")
@click.option("--material", "material_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help=f"{MATERIAL_JSON} to export [default: the reflectance solve fitted (out/reflectance.json), if "
                   "any]: Mitsuba bsdf.xml, Blender material.json + setup_material.py.")
@force_option
@click.pass_obj
def export_cmd(obj, formats, light, height, face_size, material_file, force):
    """The light (and the fitted material) in other tools' conventions -> out/export/{mitsuba,blender,opengl}/
    (README: Relight, insert, export, report)."""
    from .stages.export import FORMATS, export_stage

    scene = scene_folder(obj["scene"])
    chosen = FORMATS if "all" in formats else tuple(f for f in FORMATS if f in formats)
    export_stage(scene, chosen, light, height, face_size, obj["console"], force, obj["lock_wait"], material_file)


@_command("report")
@click.pass_obj
def report_cmd(obj):
    """out/report.html (one self-contained page) and out/report.md with figures (out/report/*.png)
    from the results on disk: input, relit, residual, light, observability; the refinement level by
    level; reflectance; bases; relighting, inserts and exports."""
    from .stages.report import report_stage

    report_stage(scene_folder(obj["scene"]), obj["console"], obj["lock_wait"])


@_command("check")
@visibility_options
@click.pass_obj
def check_cmd(obj, **kw):
    """Validate the scene folder's files (nothing is written); one line per file."""
    from .stages.check import check_scene

    scene = scene_folder(obj["scene"])
    # the parts as solve reads them: its scene.toml settings (--single-material, --no-texture) hold here too
    solve_toml = (click.get_current_context().find_root().default_map or {}).get("solve") or {}
    for line in check_scene(scene, _vis_opts(kw), parts=not solve_toml.get("single_material", False),
                            texture=not solve_toml.get("no_texture", False)):
        click.echo(line)
    click.echo(f"{scene.root}: ok")


@_command("status")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@click.pass_obj
def status_cmd(obj, as_json):
    """Show each cached stage: fresh or stale, and why."""
    from .cache import SceneCache
    from .stages import versions

    scene = scene_folder(obj["scene"])
    cache = SceneCache(scene.root)
    rows = cache.status(versions())
    if as_json:
        click.echo(json.dumps(rows, indent=1))
        return
    damaged = bool(cache.manifest().get("damaged"))
    if damaged:  # (as the stages say when they run)
        click.echo(f"{cache.dir / 'manifest.json'}: damaged; the next stage rebuilds it (calibrate and register "
                   "are recovered from camera.json and pose.json; other stages run again)")
    if not rows:
        if not damaged:
            click.echo(f"no stage has run in {scene.root}")
        return
    click.echo(f"{'stage':<12} {'state':<6} {'seconds':>8}  {'finished':<25} reason")
    for r in rows:
        click.echo(f"{r['stage']:<12} {r['state']:<6} {r['seconds'] or 0:>8.2f}  {r['finished'] or '':<25} {r['reason']}")


def main():  # pragma: no cover - console entry
    cli()
