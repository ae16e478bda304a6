"""Shared pieces of the property-based (hypothesis) tests: their settings, JSON value strategies
and the checks of the project's one error type.

The properties live with the modules they test (test_scene_files.py: the file parsers;
test_materials.py: material JSON; test_cli.py: scene.toml; test_nnls.py: `nnls_gram`;
test_light.py: the light solve on random small scenes). Each either returns a valid object or
raises the project's one error type naming the file; documents that are valid by the README's
rules must be accepted, with the values they hold.

Bulk numbers come from a numpy generator seeded by hypothesis, while hypothesis draws the
structure (sizes, density, zero and duplicate columns, noise, channel layout), so that a failure
shrinks to a small structure and a seed. Every property is derandomized (the same examples on
every run, CI included) and keeps no example database (nothing is written outside the temporary
folders). The bugs these properties found are pinned by tests with their minimal inputs:
regression tests where fixed, strict xfail where not.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from hypothesis import settings
from hypothesis import strategies as st

from pipelines.errors import InputError


def props(n: int, **kw):
    """Settings of every property here: `n` examples, no deadline (the first call of a test pays
    for imports and caches), the same examples on every run, no example database on disk."""
    return settings(max_examples=n, deadline=None, derandomize=True, database=None, **kw)


def assert_names_file(exc: InputError, path: Path) -> None:
    assert isinstance(exc, InputError)
    assert exc.path == path, (exc.path, path)
    assert str(path) in str(exc), str(exc)
    assert str(path) in exc.line()
    assert len(exc.line().splitlines()) == 1, f"the CLI prints it as one line: {exc.line()!r}"


def is_real(v) -> bool:
    """A JSON number (bool is an int in Python, but not a number in JSON)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def same_json(a, b) -> bool:
    """Equal as JSON (NaN equals NaN: the file's NaN comes back as a new float object)."""
    return json.dumps(a) == json.dumps(b)


def finite_real(v) -> bool:
    """A JSON number that is a finite float64 (an integer beyond float64 is not)."""
    if not is_real(v):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


# JSON values; integers include ones beyond float64 (json.loads reads 1e400-sized integers exactly)
ints = st.one_of(st.integers(-(2**64), 2**64), st.integers(2**1024, 2**1100), st.integers(-(2**1100), -(2**1024)))
anyfloat = st.floats(allow_nan=True, allow_infinity=True)
text = st.text(st.characters(exclude_categories=("Cs",)), max_size=8)
# TOML section and key names: any text, line breaks included (quoted names may hold them)
names = st.text(st.characters(exclude_categories=("Cs",)), max_size=8) | st.sampled_from(["a\nb", "x\ry", "\u2028"])
json_scalars = st.one_of(st.none(), st.booleans(), ints, anyfloat, text)
json_values = st.recursive(
    json_scalars,
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(text, kids, max_size=3),
    max_leaves=6)
json_numbers = st.one_of(ints, anyfloat, st.integers(-3, 3), st.sampled_from([0, 0.0, -0.0, 1e-300, 1e300]))
ABSENT = object()  # a mutation that deletes the field
wrong_values = st.one_of(json_numbers, json_values, st.just(ABSENT))


def mutate(draw, doc: dict, keys, wrong=wrong_values, most: int = 2) -> dict:
    """A valid document with up to `most` of its fields replaced by something else (or deleted),
    and maybe extra keys: most examples are valid or one mistake away from it."""
    for key in draw(st.lists(st.sampled_from(keys), max_size=most, unique=True)):
        value = draw(wrong)
        if value is ABSENT:
            doc.pop(key, None)
        else:
            doc[key] = value
    return {**draw(st.dictionaries(text, json_values, max_size=2)), **doc}


HUGE = 10**400  # a JSON integer beyond float64 (json.loads reads it as a Python int)
