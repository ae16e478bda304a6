"""What `--help` shows besides the options: each command's one-line summary (the group's command
list) and its examples, as git's and COLMAP's documentation give them: a command line that works
on the bundled sample scene, then what it does and writes.

The examples run in `spot`, a copy of sample_data/spot_sun (`cp -r sample_data/spot_sun spot`);
paths in them are relative to the folder holding `spot`. tests/test_help.py parses every example
line with the real command and checks that the sample files it names exist, so they cannot rot.
"""

from __future__ import annotations

import inspect
import re
import textwrap

SCENE = "spot"  # the examples' scene folder
SCENE_NOTE = f"{SCENE} = a copy of sample_data/spot_sun"
WIDTH = 76  # help text lines (click indents a command's help by 2; the terminal's 80 columns)

# The group's command list: each summary whole on one line (click would cut a long first sentence
# with "...": its room is 80 columns less the longest command name and the indents).
SUMMARY = {
    "calibrate": "Camera intrinsics and lens distortion from photos of a target.",
    "register": "The mesh's pose from clicked 2D-3D points (+ the photo's edges).",
    "visibility": "Shadow rays of every light direction at every pixel (cached).",
    "render": "Render the photo's view under a given light and material.",
    "solve": "Recover the light and the reflectance from the photo.",
    "compare": "Solve with every light basis: table and speed-vs-error plot.",
    "relight": "Render under the recovered or another light, or a new view.",
    "insert": "Put a virtual object, with its shadows, into the photo.",
    "export": "The light for Mitsuba 3, Blender and OpenGL / three.js.",
    "report": "out/report.md and out/report.html from the results on disk.",
    "check": "Validate the scene folder's files; writes nothing.",
    "status": "Each cached stage: fresh or stale, and why.",
}

S = f"wavelight -s {SCENE}"

# command ("" = the group) -> [(command line, what it does and writes)]
EXAMPLES: dict[str, list[tuple[str, str]]] = {
    "": [
        (f"{S} calibrate --spacing 10mm",
         "camera.json from the 15 dot-grid photos in spot/calib/."),
        (f"{S} register", "pose.json from correspondences.csv and camera.json."),
        (f"{S} solve",
         "The light and the reflectance: out/light_latlong.exr, relit.png, reflectance.json, ..."),
        (f"{S} report", "Everything on one page: out/report.html (and report.md)."),
    ],
    "calibrate": [
        (f"{S} calibrate --pattern acircles --pattern-size 4x11 --spacing 10mm",
         ("The sample's target: 4 x 11 asymmetric dots, 10 mm apart -> camera.json, with each photo's "
          "detected dots and reprojection in out/calibrate/view_00_overlay.png, ...")),
        (f"{S} calibrate --images 'calib/view_0*.png' --fix-k3",
         "Only photos view_00 to view_09 (the glob is relative to the scene), k3 held at 0."),
        (f"{S} calibrate --spacing 10mm --zero-tangent --fix-aspect",
         "A simpler lens model: no tangential distortion (p1 = p2 = 0), square pixels (fx = fy)."),
    ],
    "register": [
        (f"{S} register",
         ("pose.json from correspondences.csv, refined so the mesh's outline meets the photo's edges; "
          "out/register_overlay.png shows the outline, the clicks and their residuals.")),
        (f"{S} register --ransac on --outlier-threshold 2",
         "Always run RANSAC, counting a click more than 2 px off the fitted pose as wrong."),
        (f"{S} register --no-edge-refine", "The pose from the clicks alone."),
    ],
    "visibility": [
        (f"{S} visibility",
         ("R = 32, the upper hemisphere: .wavelight/visibility/photo-R32.h5, which solve, render and "
          "relight with the same options reuse.")),
        (f"{S} visibility -R 16 --supersample 2",
         "A coarser light, 2 x 2 rays per texel (fractional shadows): photo-R16-ss2.h5."),
        (f"{S} visibility --sphere --visibility exact",
         ("The full sphere of light, every shadow ray cast, in chunks an interrupted run resumes "
          "from: photo-R32-sphere-exact.h5.")),
    ],
    "render": [
        (f"{S} render --light spot/truth/env_latlong.exr --material spot/truth/material.json",
         ("The photo as the sample's true light and material predict it: out/render.exr, render.png, "
          "render_residual.png, and its error against the photo.")),
        ((f"{S} render --light spot/truth/env_latlong.exr --model blinn-phong "
          "--ks .3 .3 .3 --shininess 40"),
         "The same light on a glossy Blinn-Phong material (kd 1 1 1)."),
    ],
    "solve": [
        (f"{S} solve",
         ("The paper's wavelet light at R = 32, Lambertian unless a specular term pays off: "
          "out/light_latlong.exr, light_cross.png, relit.png, residual.png, reflectance.json, "
          "solve_report.json.")),
        (f"{S} solve --basis sh -R 16",
         ("Nine spherical harmonics instead of wavelets, on a coarser cube map (R = 16: 768 "
          "directions).")),
        (f"{S} solve --material spot/truth/material.json",
         "Solve the light under a known material (no reflectance fit)."),
        (f"{S} solve --reflectance blinn-phong --max-rounds 4",
         "Force a Blinn-Phong fit: at most 4 light/reflectance rounds."),
    ],
    "compare": [
        (f"{S} compare",
         ("Every basis on the scene at R = 32, with the reflectance solve fitted: out/compare.md "
          "(table), compare.json, compare.png (speed against error).")),
        (f"{S} compare -R 16 --held-out 0.2",
         "Faster, with a fifth of the pixels held out to score the bases."),
    ],
    "relight": [
        (f"{S} relight",
         ("The photo's view under the recovered light: out/relight.exr, relight.png, "
          "relight_residual.png, relight.json (its error against the photo).")),
        (f"{S} relight --name evening --rotate 120 --light-exposure -1",
         "The light turned 120 degrees about +Z, one stop darker: out/evening.exr, evening.png."),
        (f"{S} relight --light spot/truth/env_latlong.exr --name truth",
         "Under another lat-long light (here the sample's true one): out/truth.exr, truth.png."),
        (f"{S} relight --view left --name left",
         ("A scene with several photos (views/left/ ...): the left photo's view, compared with that "
          "photo: out/left.exr, left.png, left_residual.png, left.json.")),
    ],
    "insert": [
        (f"{S} insert --at 0.8 -0.6 0.25 --radius 0.25 --object-kd 0.9 0.3 0.2",
         ("A red ball beside the cow, lit by the recovered light, its shadow on the ground: "
          "out/insert.png, insert.exr, insert_render.exr, insert_shadow.png, insert.json.")),
        (f"{S} insert --at -0.7 0.5 0.15 --radius 0.15 --name ball --exposure 0",
         ("A smaller grey ball (kd 0.8) on the cow's other side, the PNG at exposure 0 (radiance 1 "
          "is white) instead of the photo's: out/ball.png, ...")),
    ],
    "export": [
        (f"{S} export",
         ("The recovered light for every tool: out/export/mitsuba/ (light.exr, emitter.xml), "
          "blender/ (light_equirect.exr, setup_world.py), opengl/ (px.exr ... nz.exr), export.json.")),
        (f"{S} export --format blender --height 256",
         ("Only Blender's world, 256 x 512: `blender --python spot/out/export/blender/setup_world.py` "
          "opens Blender with the scene lit by it.")),
        (f"{S} export --format mitsuba --light spot/truth/env_latlong.exr",
         "Convert any lat-long light (here the sample's true one) instead of the recovered one."),
    ],
    "report": [
        (f"{S} report",
         ("The report of whatever spot/out holds: open spot/out/report.html in a browser. Rerun it "
          "after any stage: it reads the results, it recomputes nothing.")),
        (f"wavelight -q -s {SCENE} report", "The same, printing only the result line."),
    ],
    "check": [
        (f"{S} check",
         ("One line per file (camera, photo, points, mesh, pose and the used pixels) or the first "
          "problem; needs camera.json (calibrate).")),
        (f"{S} check -R 16 --edge-margin 2",
         "Also check these visibility options and count the pixels they use."),
    ],
    "status": [
        (f"{S} status", "Each stage that ran: fresh or stale (and why), its time and when it finished."),
        (f"{S} status --json", "The same as JSON, with each stage's options and summary."),
    ],
}


def command_lines(line: str, width: int = WIDTH) -> list[str]:
    """A command line as the help shows it: indented by 2, broken before an option with a shell
    continuation (` \\`) where it would not fit, the continuation indented by 4."""
    groups = re.split(r" (?=--)", line)
    lines, current = [], "  " + groups[0]
    for g in groups[1:]:
        if len(current) + 1 + len(g) + 2 > width:
            lines.append(current + " \\")
            current = "    " + g
        else:
            current += " " + g
    return lines + [current]


def examples_block(examples: list[tuple[str, str]]) -> str:
    """An "Examples" section of click's help text. Each example is a paragraph click keeps as
    written (`\\b`): the command line, then what it does, wrapped here, indented under it."""
    parts = [f"Examples ({SCENE_NOTE}):"]
    for line, what in examples:
        parts.append("\n".join(["\b", *command_lines(line), _wrap(what)]))
    return "\n\n".join(parts)


def _wrap(text: str) -> str:
    """`text` wrapped under its command line; a `quoted command`, `R = 16` or a file name is never
    broken."""
    kept = re.sub(r"`[^`]*`| = ", lambda m: m.group(0).replace(" ", "\0"), text)
    return textwrap.fill(kept, WIDTH, initial_indent="      ", subsequent_indent="      ",
                         break_long_words=False, break_on_hyphens=False).replace("\0", " ")


def with_examples(help_text: str | None, name: str) -> str:
    """A command's help (its docstring) followed by its examples ("" = the group's)."""
    return inspect.cleandoc(help_text or "") + "\n\n" + examples_block(EXAMPLES[name])
