import json

import pytest

from svcode_core.config import ConfigError, SystemConfig, load_system


@pytest.mark.parametrize("name", ["cm2-mini", "cm2-v2"])
def test_preset_json_round_trip(name, tmp_path):
    system = SystemConfig.preset(name)
    path = system.save(tmp_path / "system.json")
    assert SystemConfig.load(path) == system
    assert load_system(path) == system
    assert load_system(name) == system


def test_paper_scale_geometry():
    system = SystemConfig.preset("cm2-v2")
    assert system.padded_shape == (4200, 4200)
    assert system.sub_view_size == 2400
    assert (system.patch_size, system.patch_stride) == (480, 240)
    rows = sorted({r for r, _ in system.chief_rays})
    assert rows == [1200, 2100, 3000]


def test_mini_scale_geometry():
    system = SystemConfig.preset("cm2-mini")
    assert 360 <= system.sub_view_size <= 400
    # the nine sub-views tile the padded frame exactly
    assert system.padded_shape[0] == system.sub_view_size + 2 * 144
    assert system.lens_axes[4] == (0.0, 0.0)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("sub_view_size", 0, "sub_view_size"),
        ("patch_size", 10_000, "patch_size"),
        ("rank", 0, "rank"),
        ("rank_tolerance", 1.5, "rank_tolerance"),
        ("chief_rays", ((0, 0),) * 8, "chief_rays"),
        ("chief_rays", ((0, 0),) * 8 + ((10_000, 0),), r"chief_rays\[8\]"),
        ("sensor_shape", (10, "a"), "sensor_shape"),
    ],
)
def test_bad_field_is_named(field, value, message):
    with pytest.raises(ConfigError, match=message):
        SystemConfig.preset("cm2-mini").replace(**{field: value})


def test_nested_errors_name_the_path():
    data = SystemConfig.preset("cm2-mini").to_dict()
    data["optics"]["kernel_size"] = 32
    with pytest.raises(ConfigError, match=r"optics\.kernel_size.*odd"):
        SystemConfig.from_dict(data)
    data = SystemConfig.preset("cm2-mini").to_dict()
    data["noise"]["saturation"] = float("nan")
    with pytest.raises(ConfigError, match=r"noise\.saturation"):
        SystemConfig.from_dict(data)
    data = SystemConfig.preset("cm2-mini").to_dict()
    data["optics"]["colour"] = 1
    with pytest.raises(ConfigError, match=r"optics\.colour.*unknown"):
        SystemConfig.from_dict(data)


def test_bad_json_and_unknown_preset(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text("{not json")
    with pytest.raises(ConfigError, match="not valid JSON"):
        SystemConfig.load(path)
    with pytest.raises(ConfigError, match="unknown preset"):
        SystemConfig.preset("cm3")
    with pytest.raises(ConfigError, match="neither a preset"):
        load_system("nonexistent")
    missing = SystemConfig.preset("cm2-mini").to_dict()
    del missing["sub_view_size"]
    with pytest.raises(ConfigError, match="sub_view_size"):
        SystemConfig.from_json(json.dumps(missing))
