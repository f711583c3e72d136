"""Extraction in worker processes, streamed (issue 19): the same table for any number of
workers, a resumed parallel run equal to an uninterrupted one, and the cheaper raw path
(crop read straight from a plainly stored DNG; linearisation and the mean of the repeats
fused) equal to the LibRaw / float route within float32 rounding.

The captures: two LEDs (9, 10) x two repeats of a sample (sample_2_6) and a lambert:0.8
reference at scale 0.12, one rotation, 1 spp; camera and lamps from the twin's truth."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from conftest import RIG, make_twin_captures, run_shared_folder
from glossrig.core.calibration.raw import even_crop, linearize_mean, linearize_mosaic, read_raw
from glossrig.core.errors import InputError
from glossrig.core.radiometry.hdr import combine_repeats

SIM = ("--rig", RIG, "--repeats", 2, "--scale", 0.12, "--spp", 1, "--rotations", 0, "--leds", "9,10",
       "--no-progress")


CAPTURES = {"ref": ("lambert:0.8", 6), "sample": ("sample_2_6", 7)}       # folder: (material, seed), as conftest's


def _make(d: Path) -> None:
    """conftest's tiny captures with two LEDs and two repeats (camera and lamps from the truth)."""
    make_twin_captures(d, SIM, leds=("9", "10"))


@pytest.fixture(scope="module")
def caps(tmp_path_factory):
    return run_shared_folder(tmp_path_factory, "two_led_captures", {"sim": SIM, "rig": RIG.read_text(), **CAPTURES},
                             _make)


def _inputs(d: Path):
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps

    return d / "sample", d / "ref", load_camera(d / "camera.json"), load_lamps(d / "lamps.json")


# ------------------------------------------------------------------ workers and resume

@pytest.mark.mitsuba
def test_two_workers_give_the_table_of_one_and_a_resumed_run_equals_an_uninterrupted_one(caps, tmp_path,
                                                                                         monkeypatch):
    from glossrig.core.checkpoint import WorkStore, fingerprint
    from glossrig.core.extraction.extract import extract_samples

    sample, ref, cam, lamps = _inputs(caps)
    one = extract_samples(sample, ref, cam, lamps, workers=1)
    two = extract_samples(sample, ref, cam, lamps, workers=2)
    assert len(one) > 1000 and set(one.led) == {9, 10}
    pd.testing.assert_frame_equal(one, two, check_exact=True)
    assert one.attrs["dynamic_range"] == two.attrs["dynamic_range"]
    assert one.attrs["poses"] == two.attrs["poses"] and set(one.attrs["poses"]["per_rotation"]) == {"0.0"}

    # interrupted in the parent after two of the four units were stored, workers still running
    fp = fingerprint(options={"test": "parallel resume"})
    saved = []
    real_save = WorkStore.save

    def interrupted(self, name, value):
        real_save(self, name, value)
        saved.append(name)
        if len(saved) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(WorkStore, "save", interrupted)
    with pytest.raises(KeyboardInterrupt):
        extract_samples(sample, ref, cam, lamps, workers=2, store=WorkStore(tmp_path / "w", fp))
    first = list(saved)
    saved.clear()
    store = WorkStore(tmp_path / "w", fp, resume=True)
    assert sorted(store.reused) == sorted(first)
    monkeypatch.setattr(WorkStore, "save", lambda self, name, value: (saved.append(name), real_save(self, name, value)))
    resumed = extract_samples(sample, ref, cam, lamps, workers=2, store=store)
    assert len(saved) == 2 and not set(saved) & set(first)          # only the missing units were measured
    pd.testing.assert_frame_equal(resumed, one, check_exact=True)
    assert resumed.attrs["poses"] == one.attrs["poses"]         # the poses the table records, too


@pytest.mark.mitsuba
def test_measure_capture_in_workers_equals_in_process(caps):
    from glossrig.core.extraction.extract import measure_capture

    sample, _, cam, lamps = _inputs(caps)
    a = measure_capture(sample, cam, lamps, workers=1)
    b = measure_capture(sample, cam, lamps, workers=2)
    pd.testing.assert_frame_equal(a.table, b.table, check_exact=True)
    assert list(a.geometry) == list(b.geometry) == [0.0]
    assert a.geometry[0.0].crop == b.geometry[0.0].crop


@pytest.mark.mitsuba
def test_a_pair_measured_in_one_pool_equals_each_capture_measured_alone(caps):
    """diagnose's measurement (extract.measure_pair): the sample's and the reference's tables are
    measure_capture's, the reference read only in the sample's units; a reference without one of
    the sample's units stops (extract.check_compatible) before anything is measured, naming the reference."""
    import glossrig.core.extraction.extract as ex
    from glossrig.core.capture import load_manifest

    sample, ref, cam, lamps = _inputs(caps)
    ms, mr = ex.measure_pair(sample, ref, cam, lamps, workers=2)
    alone_s, alone_r = ex.measure_capture(sample, cam, lamps, workers=1), ex.measure_capture(ref, cam, lamps, workers=1)
    pd.testing.assert_frame_equal(ms.table, alone_s.table, check_exact=True)
    pd.testing.assert_frame_equal(mr.table, alone_r.table, check_exact=True)
    assert list(ms.geometry) == list(mr.geometry) == [0.0]

    def without_led_10(folder):
        man = load_manifest(folder)
        man.images = [im for im in man.images if not (im.role == "sequence" and im.leds[0] == 10)]
        return man

    ms, mr = ex.measure_pair(without_led_10(sample), ref, cam, lamps, workers=2)      # a sample of LED 9 only
    assert set(ms.table.led) == set(mr.table.led) == {9}
    pd.testing.assert_frame_equal(mr.table, alone_r.table[alone_r.table.led == 9].reset_index(drop=True),
                                  check_exact=True)

    with pytest.raises(InputError, match="reference lacks sequences the sample has: LED 10 at 0 deg") as e:
        ex.measure_pair(sample, without_led_10(ref), cam, lamps, workers=2)        # a reference that lacks LED 10
    assert Path(str(ref)).name in str(e.value)


def test_a_bad_worker_count_is_refused():
    from glossrig.core.workers import resolve_workers, usable_cores

    assert resolve_workers(None) == usable_cores() >= 1
    for bad in (0, -2, 1.5, True):
        with pytest.raises(InputError, match="worker processes"):
            resolve_workers(bad)


def _slow_square(x: int, delay: float) -> int:
    import time

    time.sleep(delay)
    return x * x


def test_ordered_results_keep_job_order_whatever_finishes_first():
    from glossrig.core.workers import ordered_results, process_pool

    jobs = [(k, 0.3 if k % 2 == 0 else 0.0) for k in range(6)]     # even jobs finish last
    with process_pool(2) as pool:
        assert list(ordered_results(pool, _slow_square, jobs)) == [k * k for k in range(6)]
    assert list(ordered_results(None, _slow_square, jobs[:2])) == [0, 1]


def test_a_terminated_pool_stops_a_running_job_at_once():
    """WorkerPool.terminate (diagnose's frame stage on an error in the caller): the running
    60 s job is not waited for, no worker process is left behind, and its future is settled
    (a caller waiting on it does not hang) with the broken pool's error, not a result."""
    import multiprocessing
    import time
    from concurrent.futures.process import BrokenProcessPool

    from glossrig.core.workers import process_pool

    pool = process_pool(1)
    fut = pool.submit(_slow_square, 3, 60.0)
    t0 = time.monotonic()
    while not fut.running() and time.monotonic() - t0 < 30:
        time.sleep(0.05)
    t1 = time.monotonic()
    pool.terminate()
    assert time.monotonic() - t1 < 20 and not multiprocessing.active_children()
    assert fut.done() and not fut.cancelled() and isinstance(fut.exception(timeout=0), BrokenProcessPool)


def test_reference_units_follow_their_sample_units_by_the_lag():
    """extract_samples divides a pair when its reference unit arrives, so every reference unit
    must come after its sample unit; with a lag of k, k further sample units come between
    (the reference's geometry is solved beside them), and with none they alternate."""
    from glossrig.core.extraction.extract import _paired_order

    units = [(0.0, 9), (0.0, 10), (0.0, 5), (45.0, 9)]
    assert _paired_order(units, 0) == [(i, *u) for u in units for i in (0, 1)]
    for lag in (1, 2, 5):
        order = _paired_order(units, lag)
        assert sorted(order) == sorted((i, *u) for u in units for i in (0, 1))
        for k, u in enumerate(units):
            s, r = order.index((0, *u)), order.index((1, *u))
            between = sum(1 for j in order[s + 1:r] if j[0] == 0)
            assert r > s and between == min(lag, len(units) - 1 - k)


# ------------------------------------------------------------------ the raw path

@pytest.mark.mitsuba
def test_a_plain_dng_crop_is_read_as_libraw_decodes_it(caps):
    """The crop (or the whole image) copied straight from a plainly stored DNG, with or without
    the manifest's checksum, equals LibRaw's full decode (cropped), with its levels."""
    from glossrig.core.calibration.raw import _read_libraw

    files = sorted((caps / "sample").glob("*.dng"))[:3]
    for f in files:
        data = f.read_bytes()
        cfa, black, white, mosaic, origin, (w, h) = _read_libraw(f, None, None, None)      # LibRaw, whole image
        assert origin == (0, 0)
        crop = even_crop((w // 5 + 1, h // 3 + 1, w * 4 // 5, h - 3), (w, h))
        x0, y0, x1, y1 = crop
        for fast, box in ((read_raw(f, crop=crop, sha256=hashlib.sha256(data).hexdigest()), crop),
                          (read_raw(f, crop=crop), crop), (read_raw(f), (0, 0, w, h))):
            a, b, c, d = box
            np.testing.assert_array_equal(fast.mosaic, mosaic[b:d, a:c])
            assert fast.mosaic.dtype == np.uint16 and fast.origin == (a, b) and fast.full_size == (w, h)
            np.testing.assert_array_equal(fast.black, black)
            np.testing.assert_array_equal(fast.cfa, cfa)
            assert fast.white == white


@pytest.mark.mitsuba
def test_reading_a_checked_raw_leaves_no_buffer_of_its_bytes_to_the_garbage_collector(caps):
    """read_raw with a checksum hashes, parses and crops the file from one mapping of it; tifffile
    keeps the file object it parses in reference cycles that only a garbage collection frees,
    which held ~33 MB per 48 MB full-resolution DNG until one ran when it parsed a copy of the
    bytes (issue 19: a worker's memory). The mapping is closed (its pages let go) before
    read_raw returns, and no in-memory copy of the bytes is left open."""
    import gc
    import io
    import mmap

    def open_buffers() -> set[int]:
        return {id(o) for o in gc.get_objects() if isinstance(o, (io.BytesIO, mmap.mmap)) and not o.closed}

    f = sorted((caps / "sample").glob("*.dng"))[0]
    digest = hashlib.sha256(f.read_bytes()).hexdigest()
    gc.collect()
    gc.disable()                   # keep whatever cycles the read leaves
    try:
        before = open_buffers()
        frame = read_raw(f, crop=(0, 0, 8, 8), sha256=digest)
        left = open_buffers() - before
    finally:
        gc.enable()
    assert frame.mosaic.shape == (8, 8) and left == set()
    with pytest.raises(InputError, match="checksum does not match"):
        read_raw(f, crop=(0, 0, 8, 8), sha256="0" * 64)


def test_linearize_mean_is_the_correctly_rounded_mean_of_the_linearised_repeats():
    """Eq. 4.1-4.2 and 4.31 fused: within half a float32 ulp of the exact mean (float64 of
    exact integers), within one ulp of the separate float32 route, saturation marked where a
    repeat reached the white level, and fractional levels take the separate route exactly."""
    rng = np.random.default_rng(3)
    black = np.array([[600, 601], [599, 600]], np.float32)
    white = 15520.0
    for m in (1, 2, 3):
        mos = [rng.integers(500, 16383, size=(37, 52), dtype=np.uint16) for _ in range(m)]
        mos[0][:3, :3] = 15520                                   # exactly at the white level
        mean, sat = linearize_mean(mos, black, white)
        lo = np.tile(black.astype(np.float64), (19, 26))[:37, :52]
        exact = np.mean([np.clip((x - lo) / (white - lo), 0, 1) for x in mos], axis=0)
        assert mean.dtype == np.float32
        ulp = np.spacing(np.abs(mean)).astype(np.float64)
        assert np.all(np.abs(mean - exact) <= 0.5 * ulp + 1e-12)
        old, clipped = combine_repeats(np.stack([linearize_mosaic(x, black, white) for x in mos])[:, None])
        assert np.all(np.abs(mean - old[0]) <= ulp)
        np.testing.assert_array_equal(sat, clipped[0])
        assert sat[:3, :3].all() and (mean[:3, :3] <= 1.0).all()
    top = [np.full((4, 4), 16000, np.uint16)] * 3
    assert np.all(linearize_mean(top, black, white)[0] == 1.0)
    frac = np.full((2, 2), 600.5, np.float32)
    mos = [rng.integers(500, 16383, size=(8, 8), dtype=np.uint16) for _ in range(3)]
    stack = np.stack([linearize_mosaic(x, frac, white) for x in mos])
    np.testing.assert_array_equal(linearize_mean(mos, frac, white)[0],
                                  stack.mean(axis=0, dtype=np.float64).astype(np.float32))
    with pytest.raises(InputError, match="white level"):
        linearize_mean(mos, 16000, white)


def test_linearize_mean_with_fractional_levels_holds_one_repeat_at_a_time():
    """The separate (inexact) route streams the repeats (combine_repeats fed by a generator): its
    peak memory is a float64 running sum, the saturation mask, one linearised float32 repeat and
    one temporary mask (8 + 1 + 4 + 1 = 14 bytes a pixel; at the end the sum, the mask and the
    float32 result, 13), below the 17 of a previous repeat still held while the next is made
    and the 4 m of the m repeats stacked in float32 (m = 8: 32); and it equals numpy's float64 mean of the stacked float32 repeats, rounded to
    float32, bit for bit, and its saturation mask."""
    import tracemalloc

    rng = np.random.default_rng(5)
    m, shape = 8, (256, 384)
    mos = [rng.integers(500, 16383, size=shape, dtype=np.uint16) for _ in range(m)]
    frac = np.full((2, 2), 600.5, np.float32)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        mean, sat = linearize_mean(mos, frac, 15520.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    px = shape[0] * shape[1]
    assert peak < 16 * px            # between one repeat held (14) and two (17)
    stack = np.stack([linearize_mosaic(x, frac, 15520.0) for x in mos])
    np.testing.assert_array_equal(mean, stack.mean(axis=0, dtype=np.float64).astype(np.float32))
    np.testing.assert_array_equal(sat, (stack >= 1.0).any(axis=0))
    assert 0 < sat.sum() < sat.size
    with pytest.raises(InputError, match="NaN or infinite"):
        linearize_mean([np.full(shape, np.nan, np.float32)] * 2, frac, 15520.0)
