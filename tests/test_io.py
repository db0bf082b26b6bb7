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
    assert meta == {"kind": "measurement", "seed": 3}
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
    assert system == tiny_system and meta == {"kind": "reconstruction", "model": "m"}
