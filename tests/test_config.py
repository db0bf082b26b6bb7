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


def test_presets_record_pixel_sizes_over_one_field(tmp_path):
    paper, mini = SystemConfig.preset("cm2-v2"), SystemConfig.preset("cm2-mini")
    assert (paper.object_pixel_um, paper.sensor_pixel_um) == (3.25, 2.0)
    # one object pixel images onto one sensor pixel: the same ~7.8 mm field, coarser pixels
    for system in (paper, mini):
        assert system.sub_view_size * system.object_pixel_um == pytest.approx(7800.0)
        assert system.magnification == pytest.approx(2.0 / 3.25)
    assert mini.object_pixel_um == pytest.approx(paper.object_pixel_um / 0.16)
    assert SystemConfig.tiny().magnification == 0.5
    back = SystemConfig.load(mini.save(tmp_path / "system.json"))
    assert (back.object_pixel_um, back.sensor_pixel_um) == (mini.object_pixel_um, 12.5)


def test_pixel_sizes_label_but_do_not_distinguish_systems():
    mini = SystemConfig.preset("cm2-mini")
    other = mini.replace(object_pixel_um=1.5, sensor_pixel_um=None)
    assert other == mini and hash(other) == hash(mini) and other.magnification is None
    assert "sensor_pixel_um" not in other.to_dict()
    with pytest.raises(ConfigError, match="object_pixel_um: must be > 0"):
        mini.replace(object_pixel_um=0.0)
    with pytest.raises(ConfigError, match="sensor_pixel_um: must be a finite number"):
        mini.replace(sensor_pixel_um="2 um")


def test_files_without_pixel_sizes_load_as_before():
    """A system saved before the pixel sizes existed: the preset's values if it names a
    preset (so bundled models and datasets still match), else none."""
    data = SystemConfig.preset("cm2-mini").to_dict()
    del data["object_pixel_um"], data["sensor_pixel_um"]
    old = SystemConfig.from_dict(data)
    assert old == SystemConfig.preset("cm2-mini") and old.to_dict() == \
        SystemConfig.preset("cm2-mini").to_dict()
    unnamed = SystemConfig.from_dict({**data, "name": "bench rig"})
    assert unnamed.object_pixel_um is None and unnamed.magnification is None
    assert set(unnamed.to_dict()) == set(data) | {"name"}


def test_bundled_model_system_gets_the_preset_pixel_sizes():
    from svcode_core.methods.model_file import load_model, read_model_metadata
    from svcode_core.pretrained import require_bundled_weights

    path = require_bundled_weights("cm2-mini")
    mini = SystemConfig.preset("cm2-mini")
    stored = read_model_metadata(path)["system"]
    assert stored.to_dict() == mini.to_dict()
    load_model(path, system=mini)  # no difference to refuse
