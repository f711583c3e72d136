"""DNG writing (twin) and raw reading / linearising / demosaicing (core).

Covers glossrig.twin.dng.write_dng and glossrig.core.calibration.raw / core.demosaic:
round trip through rawpy/LibRaw, EXIF exposure metadata, atomic and
non-clobbering writes, corrupt files, crops, thesis eq. 4.1-4.5.
"""
from __future__ import annotations

import os
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest
import rawpy
import tifffile

from glossrig.core.capture import sha256_file
from glossrig.core.errors import InputError
from glossrig.core.calibration.raw import (channel_index, demosaic, demosaic_thesis, even_crop, linearize, linearize_mosaic,
                               read_exif, read_raw)
from glossrig.twin import dng as dngmod
from glossrig.twin.dng import write_dng

H, W = 48, 64
WHITE = 15520
BLACK = (600, 604, 608, 612)
T0 = datetime(2024, 5, 1, 12, 34, 56, 789000, tzinfo=timezone(timedelta(hours=2)))
CFAS = ["RGGB", "GRBG", "GBRG", "BGGR"]


def _mosaic(seed=0, h=H, w=W):
    rng = np.random.default_rng(seed)
    m = rng.integers(0, 16384, size=(h, w), dtype=np.uint16)
    m[0, 0], m[0, 1] = 0, 16383          # extremes survive the round trip, also above the white level
    return m


def _write(path, mosaic=None, **kw):
    args = dict(cfa="RGGB", black_level=BLACK, white_level=WHITE, exposure_s=0.0166, iso=320, aperture=11.0, time=T0)
    args.update(kw)
    return write_dng(path, _mosaic() if mosaic is None else mosaic, **args)


# ------------------------------------------------------------ round trip

@pytest.mark.parametrize("cfa", CFAS)
def test_dng_round_trip_through_libraw(tmp_path, cfa):
    m = _mosaic(1)
    _write(tmp_path / "a.dng", m, cfa=cfa)
    with rawpy.imread(str(tmp_path / "a.dng")) as raw:
        assert raw.raw_image_visible.dtype == np.uint16
        assert np.array_equal(raw.raw_image_visible, m)
        desc = raw.color_desc.decode()
        letters = "".join(desc[i] for i in raw.raw_pattern.ravel())
        assert letters == cfa
        assert raw.white_level == WHITE
        blpc = raw.black_level_per_channel
        assert [blpc[i] for i in raw.raw_pattern.ravel()] == list(BLACK)

    frame = read_raw(tmp_path / "a.dng")
    assert np.array_equal(frame.mosaic, m)
    assert "".join("RGB"[i] for i in frame.cfa.ravel()) == cfa
    assert frame.black.ravel().tolist() == list(BLACK)
    assert frame.white == WHITE
    assert frame.origin == (0, 0) and frame.full_size == (W, H)
    assert np.array_equal(frame.channel_index(), channel_index((H, W), cfa))


@pytest.mark.parametrize("exposure,iso,aperture", [(1 / 4000, 320, 11.0), (0.0166, 320, 11.0), (30.0, 3200, 11.0),
                                                   (2.0, 102400, 5.6)])
def test_exif_exposure_metadata_read_back(tmp_path, exposure, iso, aperture):
    _write(tmp_path / "e.dng", exposure_s=exposure, iso=iso, aperture=aperture)
    frame = read_raw(tmp_path / "e.dng")
    assert frame.exposure_s == pytest.approx(exposure, rel=1e-6)
    assert frame.iso == iso
    assert frame.aperture == pytest.approx(aperture, rel=1e-6)
    assert frame.timestamp == T0
    assert frame.timestamp.utcoffset() == timedelta(hours=2)
    assert frame.camera == "Nikon D750 (glossrig twin)"
    # The exposure tags sit in a real EXIF IFD, as cameras write them.
    with tifffile.TiffFile(tmp_path / "e.dng") as tf:
        exif = tf.pages[0].tags["ExifTag"].value
    assert "ExposureTime" in exif and "FNumber" in exif and "DateTimeOriginal" in exif


def test_naive_time_and_description(tmp_path):
    t = datetime(2023, 1, 2, 3, 4, 5, 6000)
    _write(tmp_path / "n.dng", time=t, extra_description="rotation 45", unique_model="glossrig twin 1")
    info = read_exif(tmp_path / "n.dng")
    assert info.timestamp == t and info.timestamp.tzinfo is None
    assert info.camera == "glossrig twin 1"
    with tifffile.TiffFile(tmp_path / "n.dng") as tf:
        assert tf.pages[0].description == "rotation 45"


def _tiffep_dng(path, mosaic, exif_tags):
    """A minimal DNG with the EXIF tags in IFD0 (TIFF/EP placement), written
    independently of write_dng."""
    tags = [(33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True), (50706, "B", 4, (1, 4, 0, 0), True),
            (50708, "s", 0, "other camera", True), (50713, "H", 2, (2, 2), True), (50714, "I", 4, BLACK, True),
            (50717, "I", 1, WHITE, True)] + exif_tags
    tifffile.imwrite(path, mosaic, photometric=32803, metadata=None, extratags=tags)


def test_exif_in_ifd0_and_manifest_fallback(tmp_path):
    m = _mosaic(2)
    _tiffep_dng(tmp_path / "ep.dng", m, [(33434, "2I", 1, (1, 250), True), (33437, "2I", 1, (8, 1), True),
                                         (34855, "H", 1, 200, True), (36867, "s", 0, "2022:07:08 09:10:11", True)])
    f = read_raw(tmp_path / "ep.dng")
    assert (f.exposure_s, f.iso, f.aperture) == (pytest.approx(0.004), 200, 8.0)
    assert f.timestamp == datetime(2022, 7, 8, 9, 10, 11)
    assert np.array_equal(f.mosaic, m) and f.camera == "other camera"
    # The manifest's values agree within tolerance: the file's win.
    assert read_raw(tmp_path / "ep.dng", exposure_s=0.0041, iso=200).exposure_s == pytest.approx(0.004)
    # A shot that disagrees with the manifest is caught.
    with pytest.raises(InputError, match="ep.dng.*exposure time.*disagrees"):
        read_raw(tmp_path / "ep.dng", exposure_s=0.008)

    _tiffep_dng(tmp_path / "noexif.dng", m, [])
    with pytest.raises(InputError, match="noexif.dng.*no exposure time"):
        read_raw(tmp_path / "noexif.dng")
    when = datetime(2020, 1, 1, tzinfo=timezone.utc)
    f = read_raw(tmp_path / "noexif.dng", exposure_s=0.5, iso=320, aperture=11, timestamp=when)
    assert (f.exposure_s, f.iso, f.aperture, f.timestamp) == (0.5, 320, 11, when)
    g = read_raw(tmp_path / "noexif.dng", exposure_s=0.5)
    assert g.iso is None and g.aperture is None and g.timestamp is None


# -------------------------------------------------------- safe writing

def test_refuses_to_overwrite(tmp_path):
    p = tmp_path / "x.dng"
    digest = _write(p)
    assert digest == sha256_file(p)
    before = p.read_bytes()
    with pytest.raises(InputError, match="x.dng.*refusing to overwrite"):
        _write(p, _mosaic(5))
    assert p.read_bytes() == before
    digest2 = _write(p, _mosaic(5), overwrite=True)
    assert digest2 != digest and digest2 == sha256_file(p)
    assert np.array_equal(read_raw(p).mosaic, _mosaic(5))
    assert sorted(os.listdir(tmp_path)) == ["x.dng"]


def test_atomic_write_leaves_no_temporary_file(tmp_path, monkeypatch):
    _write(tmp_path / "ok.dng")
    assert sorted(os.listdir(tmp_path)) == ["ok.dng"]

    def boom(*a, **k):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(dngmod.tifffile, "imwrite", boom)
    with pytest.raises(OSError, match="simulated"):
        _write(tmp_path / "bad.dng")
    assert sorted(os.listdir(tmp_path)) == ["ok.dng"]


def test_write_rejects_bad_arguments(tmp_path):
    with pytest.raises(InputError, match="black_level"):
        _write(tmp_path / "b.dng", black_level=(600, 600, 600))
    with pytest.raises(InputError, match="exposure_s"):
        _write(tmp_path / "b.dng", exposure_s=0)
    with pytest.raises(InputError, match="2-D"):
        _write(tmp_path / "b.dng", np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(InputError, match="integers"):
        _write(tmp_path / "b.dng", np.zeros((4, 4), np.float32))
    with pytest.raises(InputError, match="CFA"):
        _write(tmp_path / "b.dng", cfa="RGBX")
    with pytest.raises(InputError, match="does not exist"):
        _write(tmp_path / "missing" / "b.dng")
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------- corrupt input

def test_corrupt_files_give_input_error_naming_the_file(tmp_path):
    _write(tmp_path / "good.dng")
    data = (tmp_path / "good.dng").read_bytes()
    (tmp_path / "half.dng").write_bytes(data[: len(data) // 2])
    (tmp_path / "head.dng").write_bytes(data[:200])
    (tmp_path / "garbage.nef").write_bytes(np.random.default_rng(0).bytes(5000))
    (tmp_path / "empty.dng").write_bytes(b"")
    tifffile.imwrite(tmp_path / "plain.tif", np.zeros((8, 8), np.uint16))
    with pytest.raises(InputError, match=r"half\.dng.*truncated"):
        read_raw(tmp_path / "half.dng")
    for name in ("head.dng", "garbage.nef", "empty.dng", "plain.tif"):
        with pytest.raises(InputError) as e:
            read_raw(tmp_path / name)
        assert e.value.path == str(tmp_path / name)
    with pytest.raises(InputError, match="not found"):
        read_raw(tmp_path / "nope.dng")


# ------------------------------------------------------------------ crop

def test_crop_keeps_cfa_phase(tmp_path):
    m = _mosaic(3)
    _write(tmp_path / "c.dng", m, cfa="GBRG")
    f = read_raw(tmp_path / "c.dng", crop=(10, 4, 31, 20))
    assert np.array_equal(f.mosaic, m[4:20, 10:31])
    assert f.origin == (10, 4) and f.full_size == (W, H)
    assert "".join("RGB"[i] for i in f.cfa.ravel()) == "GBRG"
    assert f.black.ravel().tolist() == list(BLACK)
    with pytest.raises(InputError, match="c.dng.*odd offset"):
        read_raw(tmp_path / "c.dng", crop=(3, 4, 20, 20))
    with pytest.raises(InputError, match="outside"):
        read_raw(tmp_path / "c.dng", crop=(0, 0, W + 2, 10))
    assert even_crop((3, 5, 20, 21), (W, H)) == (2, 4, 20, 22)
    assert even_crop((-5, 1, 99, 99), (W, H)) == (0, 0, W, H)


# ------------------------------------------------------------ linearise

def test_linearize_normalises_and_clips():
    black = np.array([[600, 604], [608, 612]], np.float32)
    m = np.array([[600, 604, 500, 0],
                  [608, 612, 15520, 16383],
                  [8060, 604 + 7458, 600, 604],
                  [608, 612, 15519, 15520]], np.uint16)
    lin = linearize_mosaic(m, black, WHITE)
    assert lin.dtype == np.float32
    assert lin[0, 0] == lin[0, 1] == lin[1, 0] == lin[1, 1] == 0.0          # at black
    assert lin[0, 2] == 0.0 and lin[0, 3] == 0.0                           # below black: clipped
    assert lin[1, 2] == 1.0 and lin[1, 3] == 1.0 and lin[3, 3] == 1.0      # saturated: exactly 1
    assert lin[3, 2] < 1.0
    assert lin[2, 0] == pytest.approx((8060 - 600) / (WHITE - 600), rel=1e-6)
    assert lin[2, 1] == pytest.approx(7458 / (WHITE - 604), rel=1e-6)
    # The thesis's printed min(max(x, 1), 0) would give 0 everywhere.
    assert 0.4 < lin[2, 0] < 0.6


def test_linearize_frame(tmp_path):
    m = _mosaic(4)
    _write(tmp_path / "l.dng", m)
    f = read_raw(tmp_path / "l.dng")
    lin = linearize(f)
    expect = np.clip((m.astype(float) - np.tile(np.reshape(BLACK, (2, 2)), (H // 2, W // 2))) / (WHITE - np.tile(
        np.reshape(BLACK, (2, 2)), (H // 2, W // 2))), 0, 1)
    assert np.allclose(lin, expect, atol=1e-6)


# ------------------------------------------------------------ demosaic

def _flat_mosaic(cfa, rgb, h=16, w=20):
    return np.choose(channel_index((h, w), cfa), rgb).astype(np.float32)


def test_channel_index():
    ci = channel_index((3, 5), "RGGB")
    assert ci.tolist() == [[0, 1, 0, 1, 0], [1, 2, 1, 2, 1], [0, 1, 0, 1, 0]]
    assert channel_index((2, 2), "BGGR").tolist() == [[2, 1], [1, 0]]


@pytest.mark.parametrize("cfa", CFAS)
def test_demosaic_channel_order_on_flat_colour(cfa):
    rgb = (0.2, 0.5, 0.8)
    out = demosaic(_flat_mosaic(cfa, rgb), cfa)
    assert out.shape == (16, 20, 3) and out.dtype == np.float32
    for c in range(3):
        assert np.allclose(out[..., c], rgb[c], atol=1e-4), (cfa, c)      # everywhere, border included
    u16 = demosaic((_flat_mosaic(cfa, rgb) * 10000).astype(np.uint16), cfa)
    assert u16.dtype == np.uint16 and tuple(u16[7, 9]) == (2000, 5000, 8000)


def test_thesis_demosaic_matches_inside_and_darkens_border():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:32, 0:40]
    rgb = np.stack([0.3 + 0.01 * xx, 0.5 + 0.005 * yy, 0.2 + 0.004 * (xx + yy)], -1)   # smooth scene
    m = np.choose(channel_index((32, 40), "RGGB"), np.moveaxis(rgb, -1, 0)).astype(np.float32)
    m += rng.normal(0, 1e-3, m.shape).astype(np.float32)
    cv, th = demosaic(m, "RGGB"), demosaic_thesis(m, "RGGB")
    assert np.abs(cv[2:-2, 2:-2] - th[2:-2, 2:-2]).max() < 1e-4      # same bilinear kernels inside
    # Border: the thesis's zero padding darkens, OpenCV does not (the gain of departing from eq. 4.4).
    flat = _flat_mosaic("RGGB", (0.2, 0.5, 0.8))
    cv, th = demosaic(flat, "RGGB"), demosaic_thesis(flat, "RGGB")
    truth = np.array([0.2, 0.5, 0.8], np.float32)
    err_cv = np.abs(cv[0] - truth).max()
    err_th = np.abs(th[0] - truth).max()
    assert err_cv < 1e-4 and err_th > 0.1
    assert np.allclose(th[4:-4, 4:-4], truth, atol=1e-6)


# ------------------------------------------------ checksums (issue #16)

def _one_image_capture(folder, role="sequence"):
    """A capture folder whose manifest lists one DNG with its sha256, as the capture tools write it."""
    import json

    folder.mkdir()
    digest = _write(folder / "seq.dng")
    im = {"file": "seq.dng", "role": role, "leds": [9], "rotation": 0.0, "repeat": 0, "exposure_s": 0.0166,
          "iso": 320, "aperture": 11.0, "time": T0.isoformat(), "sha256": digest}
    (folder / "capture.json").write_text(json.dumps({"rig": "rig.toml", "material": "m", "complete": True,
                                                     "images": [im]}))
    return folder / "seq.dng"


def test_capture_images_are_read_only_if_their_checksum_matches_the_manifest(tmp_path):
    """A few flipped bytes in the pixel data still decode - into wrong values, silently - so
    every capture read goes through Manifest.read_raw, which compares the manifest's sha256."""
    from glossrig.core.capture import load_manifest

    f = _one_image_capture(tmp_path / "cap")
    man = load_manifest(tmp_path / "cap")
    good = man.read_raw(man.images[0])
    assert np.array_equal(good.mosaic, _mosaic()) and good.exposure_s == pytest.approx(0.0166)
    assert np.array_equal(man.read_raw(man.images[0], crop=(2, 4, 10, 12)).mosaic, _mosaic()[4:12, 2:10])
    with tifffile.TiffFile(f) as tf:
        start = int(tf.pages[0].dataoffsets[0])     # the pixel strip
    data = bytearray(f.read_bytes())
    for k in range(0, 400, 7):                      # flip bytes inside it
        data[start + 100 + k] ^= 0xFF
    f.write_bytes(bytes(data))
    assert not np.array_equal(read_raw(f).mosaic, _mosaic())        # decodes fine, but wrong: the hazard
    with pytest.raises(InputError, match=r"seq\.dng: checksum does not match capture\.json \(file changed since capture\)"):
        man.read_raw(man.images[0])
    with pytest.raises(InputError, match="seq.dng: checksum does not match capture.json"):
        read_raw(f, sha256=man.images[0].sha256)


def test_rewriting_a_capture_on_purpose_updates_its_checksums(tmp_path):
    """Tools that rewrite raw values on purpose (glossrig.twin.rewrite_raw.rewrite_capture) keep the
    manifest honest, so the checksum check lets their captures through."""
    from glossrig.core.capture import load_manifest
    from glossrig.twin.rewrite_raw import rewrite_capture

    _one_image_capture(tmp_path / "src")
    rewrite_capture(tmp_path / "src", tmp_path / "dst", "black_level_offset", 5)
    man = load_manifest(tmp_path / "dst")
    got = man.read_raw(man.images[0]).mosaic
    assert np.array_equal(got, np.clip(_mosaic().astype(int) + 5, 0, WHITE))


def test_a_rewritten_effect_is_in_the_dark_pixels_too(tmp_path):
    """A raw file holds integers: rounding the rewritten value to the nearest one would leave every
    pixel within 6 DN of black as it was under a shutter error of 8 % of the frame's time (round(1.08 x)
    = x), so the effect would be missing where it is largest. The rewrite rounds stochastically: over the
    pixels of one level x above black the mean written value is 1.08 x, within 4 standard errors of the
    rounding (its variance is at most 1/4 DN^2: sd 0.5 / sqrt(n)), for every x from 1 to 12 DN; a
    nearest-integer rewrite misses it by 0.08 x (0.08-0.48 DN for x <= 6) - tens of those errors."""
    import json

    from glossrig.core.capture import load_manifest
    from glossrig.twin.rewrite_raw import rewrite_capture

    rng = np.random.default_rng(3)
    x = rng.integers(1, 13, size=(H, W))
    black = np.tile(np.reshape(BLACK, (2, 2)), (H // 2, W // 2))
    src = tmp_path / "src"
    src.mkdir()
    digest = _write(src / "seq.dng", (black + x).astype(np.uint16), exposure_s=0.00025)
    im = {"file": "seq.dng", "role": "sequence", "leds": [9], "rotation": 0.0, "repeat": 0, "exposure_s": 0.00025,
          "iso": 320, "aperture": 11.0, "time": T0.isoformat(), "sha256": digest}
    (src / "capture.json").write_text(json.dumps({"rig": "rig.toml", "material": "m", "complete": True,
                                                  "images": [im]}))
    rewrite_capture(src, tmp_path / "dst", "shutter_error", 2e-5)
    man = load_manifest(tmp_path / "dst")
    got = man.read_raw(man.images[0]).mosaic.astype(float) - black
    for level in range(1, 13):
        sel = x == level
        n = int(sel.sum())
        assert abs(got[sel].mean() - 1.08 * level) < 4 * 0.5 / np.sqrt(n), (level, got[sel].mean(), n)


@pytest.mark.parametrize("effect,value", [("shutter_error", 0.002), ("channel_response", 0.05)])
def test_rewritten_real_camera_effects_follow_their_models(tmp_path, effect, value):
    """The blind study's real-camera effects written into the DNGs (glossrig.twin.rewrite_raw):
    a shutter error scales the signal above black by (t + d) / t for the frame's nominal t; a
    per-channel response compresses only the red pixels, x -> x (1 - c x / (white - black)).
    Unsaturated pixels within 1 DN (the rewrite rounds to integers stochastically), saturated ones
    unchanged."""
    from glossrig.core.capture import load_manifest
    from glossrig.twin.rewrite_raw import rewrite_capture

    _one_image_capture(tmp_path / "src")
    rewrite_capture(tmp_path / "src", tmp_path / "dst", effect, value)
    fr = load_manifest(tmp_path / "dst").read_raw(load_manifest(tmp_path / "dst").images[0])
    dn = _mosaic().astype(float)
    black = np.tile(np.reshape(BLACK, (2, 2)), (H // 2, W // 2)).astype(float)
    x = dn - black
    if effect == "shutter_error":
        want = black + x * (0.0166 + value) / 0.0166
    else:
        red = np.zeros((H, W), bool)
        red[0::2, 0::2] = True                    # RGGB
        want = np.where(red, black + x * (1 - value * np.maximum(x, 0) / (WHITE - black)), dn)
    want = np.clip(np.where(dn >= WHITE, dn, want), 0, WHITE)
    assert np.max(np.abs(fr.mosaic.astype(float) - want)) < 1.0
    assert np.all(fr.mosaic[dn >= WHITE] == WHITE)                     # saturated stay saturated
    assert not np.array_equal(fr.mosaic, np.clip(dn, 0, WHITE).astype(np.uint16))   # the effect is there
