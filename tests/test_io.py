import numpy as np
import pytest
import tifffile

from svcode_core.io import read_tiff, write_json_atomic, write_tiff


def test_tiff_round_trip_records_system(tmp_path, mini_system):
    data = np.random.default_rng(0).random((3, 5, 7)).astype(np.float64)
    path = write_tiff(tmp_path / "a" / "m.tif", data, mini_system, kind="measurement",
                      extra={"seed": 3})
    array, system, meta = read_tiff(path)
    assert array.dtype == np.float32
    np.testing.assert_array_equal(array, data.astype(np.float32))
    assert system == mini_system
    assert meta == {"kind": "measurement", "seed": 3, "pixel_size_um": 20.3125}
    assert not list(path.parent.glob("*.partial"))


def test_foreign_tiff_uses_system_json_beside(tmp_path, mini_system):
    tifffile.imwrite(tmp_path / "raw.tif", np.zeros((4, 4), np.uint16))
    assert read_tiff(tmp_path / "raw.tif")[1] is None
    mini_system.save(tmp_path / "system.json")
    array, system, meta = read_tiff(tmp_path / "raw.tif")
    assert system == mini_system and meta == {} and array.dtype == np.uint16


def test_errors(tmp_path, mini_system):
    with pytest.raises(FileNotFoundError):
        read_tiff(tmp_path / "missing.tif")
    with pytest.raises(TypeError):
        write_tiff(tmp_path / "x.tif", np.zeros(3), mini_system, extra={"bad": object()})
    assert not (tmp_path / "x.tif").exists()
    write_json_atomic(tmp_path / "p.json", {"done": [1, 2]})
    assert (tmp_path / "p.json").read_text().strip().startswith("{")


@pytest.mark.parametrize("shape, axes", [((6, 5), "YX"), ((3, 6, 5), "TYX")])
def test_ome_tiff_round_trip_keeps_the_system(tiny_system, tmp_path, shape, axes):
    data = np.arange(np.prod(shape), dtype=np.float32).reshape(shape)
    path = write_tiff(tmp_path / "rec.ome.tif", data, tiny_system, kind="reconstruction",
                      extra={"model": "m"})
    with tifffile.TiffFile(path) as tif:
        assert tif.is_ome and tif.series[0].axes == axes
    back, system, meta = read_tiff(path)
    np.testing.assert_array_equal(back, data)
    assert system == tiny_system
    assert meta == {"kind": "reconstruction", "model": "m", "pixel_size_um": 10.0}


def test_tiff_records_the_object_pixel_size_for_other_software(tmp_path, mini_system):
    """Resolution tags in pixels per centimetre (what ImageJ and viewers read); a raw
    frame gets the object-space size too, so it overlays its reconstruction."""
    path = write_tiff(tmp_path / "frame.tif", np.zeros((4, 6)), mini_system, kind="measurement")
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        assert int(page.resolutionunit) == tifffile.RESUNIT.CENTIMETER
        assert page.get_resolution() == pytest.approx((1e4 / 20.3125,) * 2)
    assert read_tiff(path)[2]["pixel_size_um"] == 20.3125


def test_ome_tiff_records_physical_size_in_micrometres(tmp_path, tiny_system):
    path = write_tiff(tmp_path / "views.ome.tif", np.zeros((9, 6, 5)), tiny_system,
                      kind="views")
    with tifffile.TiffFile(path) as tif:
        pixels = tif.series[0].axes, tif.ome_metadata
    assert pixels[0] == "CYX"
    assert 'PhysicalSizeX="10.0" PhysicalSizeXUnit="µm"' in pixels[1]
    assert 'PhysicalSizeY="10.0" PhysicalSizeYUnit="µm"' in pixels[1]
    assert read_tiff(path)[2]["pixel_size_um"] == 10.0


def test_pixel_size_given_unknown_or_foreign(tmp_path, tiny_system):
    given = write_tiff(tmp_path / "psfs.tif", np.zeros((3, 3)), tiny_system,
                       pixel_size_um=2.5)
    assert read_tiff(given)[2]["pixel_size_um"] == 2.5
    unknown = tiny_system.replace(object_pixel_um=None)
    for system in (None, unknown):
        path = write_tiff(tmp_path / "plain.tif", np.zeros((3, 3)), system)
        assert "pixel_size_um" not in read_tiff(path)[2]
        with tifffile.TiffFile(path) as tif:
            assert int(tif.pages[0].resolutionunit) == tifffile.RESUNIT.NONE
    tifffile.imwrite(tmp_path / "fiji.tif", np.zeros((4, 4), np.uint16), imagej=True,
                     resolution=(2.0, 2.0), metadata={"unit": "\\u00B5m"})
    tifffile.imwrite(tmp_path / "inch.tif", np.zeros((4, 4), np.uint16),
                     resolution=(100.0, 100.0), resolutionunit="INCH")
    assert read_tiff(tmp_path / "fiji.tif")[2] == {"pixel_size_um": 0.5}
    assert read_tiff(tmp_path / "inch.tif")[2] == {"pixel_size_um": 254.0}
