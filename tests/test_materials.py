"""Material JSON (pipelines.model.materials): `Material.from_json` returns a valid material or
raises ValueError on random documents (hypothesis), round trips, and the regressions it found."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import event, given
from hypothesis import strategies as st

from pipelines.model.materials import MODELS, Material
from property_helpers import HUGE, finite_real, json_numbers, mutate, props, text, wrong_values


@props(100)
@given(kd=st.lists(st.floats(0, 1e3), min_size=3, max_size=3), ks=st.lists(st.floats(0, 1e3), min_size=3, max_size=3),
       n=st.floats(0, 1e4), model=st.sampled_from(tuple(MODELS)))
def test_material_round_trip(kd, ks, n, model):
    mat = Material(tuple(kd), tuple(ks), n, model)
    assert Material.from_json(json.loads(json.dumps(mat.to_json()))) == mat


@st.composite
def material_docs(draw):
    """A valid material document (some of model/type, kd, ks, n/shininess) with up to two fields
    replaced by other values."""
    names = st.sampled_from(list(MODELS) + ["diffuse", "Lambertian", "BlinnPhong", "blinn_phong", "PHONG"])
    rgb = st.one_of(st.floats(0, 10), st.integers(0, 3), st.lists(st.floats(0, 10), min_size=3, max_size=3))
    fields = {"model": names, "type": names, "kd": rgb, "ks": rgb, "n": st.floats(0, 1e3),
              "shininess": st.floats(0, 1e3)}
    doc = {key: draw(valid) for key, valid in fields.items() if draw(st.booleans())}
    wrong = st.one_of(wrong_values, text, st.lists(json_numbers, max_size=4), st.sampled_from([-1, -0.5, None]))
    return mutate(draw, doc, list(fields), wrong)


@props(150)
@given(doc=material_docs())
def test_material_from_json_returns_a_valid_material_or_value_error(doc):
    try:
        mat = Material.from_json(doc)
    except ValueError:
        # the reason must be real: no well-formed document is refused
        model = str(doc.get("model", doc.get("type", "lambert"))).lower()
        model = {"diffuse": "lambert", "lambertian": "lambert", "blinnphong": "blinn-phong",
                 "blinn_phong": "blinn-phong"}.get(model, model)

        def rgb_ok(v):
            return v is None or (finite_real(v) and v >= 0) or (
                isinstance(v, list) and len(v) == 3 and all(finite_real(x) and x >= 0 for x in v))
        n = doc.get("n", doc.get("shininess", 1.0))
        assert not (model in MODELS and rgb_ok(doc.get("kd")) and rgb_ok(doc.get("ks"))
                    and finite_real(n) and n >= 0), f"a valid material was rejected: {doc}"
        event("rejected")
        return
    event("accepted")
    assert mat.model in MODELS
    for v in (mat.kd, mat.ks):
        assert len(v) == 3 and all(type(x) is float and math.isfinite(x) and x >= 0 for x in v)
    assert type(mat.shininess) is float and math.isfinite(mat.shininess) and mat.shininess >= 0


# -- regressions: bugs the properties found, each with its minimal input ----------------------
# Each failed on commit 40420ef (a traceback, or a wrong acceptance); each passes once its bug is fixed.

@pytest.mark.parametrize("doc", [[1, 2, 3], None, "lambert", {"n": HUGE}, {"kd": [HUGE, 0, 0]}])
def test_material_from_json_bad_documents_are_value_errors(doc):
    """Was: Material.from_json called data.get() before its isinstance(data, dict) check
    (AttributeError), and float() of a huge integer n or kd overflowed (OverflowError, which
    stages.material_from_options does not catch either)."""
    with pytest.raises(ValueError):
        Material.from_json(doc)
