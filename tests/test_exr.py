import numpy as np
import pytest

from odmv.io.exr import COMPRESSIONS, ExrError, exr_channels, read_channel, read_exr, write_exr


@pytest.mark.parametrize("dtype", [np.float32, np.float16])
@pytest.mark.parametrize("compression", list(COMPRESSIONS))
def test_round_trip_is_bit_exact(tmp_path, dtype, compression):
    rng = np.random.default_rng(0)
    a = (rng.standard_normal((37, 53)) * 100).astype(dtype)
    a[0, 0], a[1, 1] = np.nan, np.inf
    path = write_exr(tmp_path / "a.exr", {"Z": a}, compression=compression)
    b = read_channel(path, "Z")
    assert b.dtype == a.dtype and b.shape == a.shape
    bits = np.uint32 if dtype == np.float32 else np.uint16
    assert np.array_equal(a.view(bits), b.view(bits))


def test_multi_channel_round_trip_keeps_names_and_caller_arrays(tmp_path):
    chans = {v: np.full((8, 12), i, np.float32) for i, v in enumerate(["right", "down", "up"])}
    keep = {k: a.copy() for k, a in chans.items()}
    write_exr(tmp_path / "m.exr", chans, compression="zstd")
    assert exr_channels(tmp_path / "m.exr") == {k: (8, 12) for k in chans}
    back = read_exr(tmp_path / "m.exr")
    for k in chans:
        assert np.array_equal(back[k], keep[k]) and np.array_equal(chans[k], keep[k])


def test_write_is_atomic_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "x.exr"
    write_exr(path, {"Y": np.ones((4, 4), np.float32)})
    with pytest.raises(ExrError):
        write_exr(path, {"Y": np.ones((4, 4), np.float64)})  # rejected before touching disk
    assert read_channel(path, "Y").sum() == 16
    assert [p.name for p in tmp_path.iterdir()] == ["x.exr"]


def _one_line(err: ExrError, path) -> None:
    msg = str(err)
    assert "\n" not in msg and msg.startswith(str(path))


def test_truncated_file_raises_one_line_error(tmp_path):
    good = write_exr(tmp_path / "g.exr", {"Y": np.random.rand(64, 64).astype(np.float32)})
    bad = tmp_path / "t.exr"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ExrError, match="truncated") as e:
        read_exr(bad)
    _one_line(e.value, bad)


def test_text_file_named_exr_raises_one_line_error(tmp_path):
    bad = tmp_path / "text.exr"
    bad.write_text("this is not an image\n")
    with pytest.raises(ExrError, match="not an OpenEXR file") as e:
        read_exr(bad)
    _one_line(e.value, bad)


def test_missing_file_and_missing_channel(tmp_path):
    with pytest.raises(ExrError, match="no such file"):
        read_exr(tmp_path / "none.exr")
    path = write_exr(tmp_path / "c.exr", {"Y": np.zeros((2, 2), np.float32)})
    with pytest.raises(ExrError, match="missing channel 'Z'") as e:
        read_channel(path, "Z")
    _one_line(e.value, path)
