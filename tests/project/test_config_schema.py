"""The config schema bounds every number: a sign or a misplaced digit is refused at start-up."""

from __future__ import annotations

import pytest

from pipeline.config import SCHEMA_PATH, _read_yaml, load_config, range_text, validate_config
from pipeline.errors import InputError

_LOW = ("minimum", "exclusiveMinimum")
_HIGH = ("maximum", "exclusiveMaximum")
#: a number property may go without a bound when its schema says why under this key
UNBOUNDED_REASON = "x-unbounded"


def _numbers(schema: dict, path: str = ""):
    """(dotted path, schema) of every number or integer the schema describes, array items and
    open-ended mappings' values included."""
    types = schema.get("type")
    types = types if isinstance(types, list) else [types]
    if "number" in types or "integer" in types:
        yield path, schema
    for key, sub in (schema.get("properties") or {}).items():
        yield from _numbers(sub, f"{path}.{key}" if path else key)
    for key in ("items", "additionalProperties"):
        if isinstance(schema.get(key), dict):
            yield from _numbers(schema[key], f"{path}[]" if key == "items" else f"{path}.*")


def test_every_number_of_the_schema_has_a_range():
    numbers = list(_numbers(_read_yaml(SCHEMA_PATH)))
    assert len(numbers) > 80           # the walk reaches every section's numbers
    unbounded = [path for path, sub in numbers
                 if not (any(k in sub for k in _LOW) and any(k in sub for k in _HIGH))
                 and not str(sub.get(UNBOUNDED_REASON, "")).strip()]
    assert not unbounded, f"numbers without a minimum and a maximum (or a stated reason): {unbounded}"


def test_every_default_lies_inside_its_range():
    """load_config validates the defaults it fills: one outside its own range would stop every run."""
    load_config()


@pytest.mark.parametrize("key, value, expected", [
    (("dark", "hot_pixel_threshold_sigma"), -6, "-6 is outside its range [1, 100]"),
    (("field", "confidence_level"), 1.0, "1.0 is outside its range (0, 1)"),
    (("linearity", "mask_half_angle_deg"), 500, "500 is outside its range (0, 90]"),
])
def test_a_value_outside_its_range_is_refused_in_one_line(key, value, expected):
    section, name = key
    with pytest.raises(InputError) as err:
        validate_config({"dataset": "d", section: {name: value}})
    assert str(err.value) == f"{SCHEMA_PATH}: config {section}.{name}: {expected}"


def test_range_text():
    assert range_text({"minimum": 0}) == "[0, inf)"
    assert range_text({"exclusiveMinimum": 0, "exclusiveMaximum": 1}) == "(0, 1)"
    assert range_text({"maximum": 9}) == "(-inf, 9]"
