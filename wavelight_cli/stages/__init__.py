"""The cached stages, one module each: plan (a declared `cache.Stage`), run the controller in
`pipelines.controllers`, write the outputs, record them (`cache.run_stage`)."""

from __future__ import annotations


def versions() -> dict[str, int]:
    """The current version of every stage kind (what `status` compares the manifest with)."""
    from . import calibrate, export, insert, register, relight, render, solve, visibility

    return {"calibrate": calibrate.VERSION, "register": register.VERSION, "visibility": visibility.VERSION,
            "render": render.VERSION, "solve": solve.VERSION, "compare": solve.COMPARE_VERSION,
            "relight": relight.VERSION, "insert": insert.VERSION, "export": export.VERSION}
