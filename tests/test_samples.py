"""The samples table (design.md): validating Parquet reader and writer."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from glossrig.core.errors import InputError
from glossrig.core.samples import COLUMNS, luminance, read_samples, validate_samples, ward_samples, write_samples
from glossrig.core.models.ward import WardParams, ward_from_angles


def table(n=50, seed=0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    geo = pd.DataFrame({
        "theta_in": rng.uniform(0, 1.4, n), "phi_in": rng.uniform(0, 2 * math.pi, n),
        "theta_out": rng.uniform(0, 1.4, n), "phi_out": rng.uniform(0, 2 * math.pi, n),
        "theta_h": rng.uniform(0, 1.4, n), "phi_h": rng.uniform(0, 2 * math.pi, n),
        "theta_d": rng.uniform(0, 1.4, n), "phi_d": rng.uniform(0, 2 * math.pi, n),
        "u": rng.integers(0, 300, n), "v": rng.integers(0, 200, n), "led": rng.integers(5, 13, n),
        "rotation": rng.choice([-45.0, 0.0, 45.0, 90.0], n)})
    return ward_samples(geo, WardParams(0.05, 0.01, 0.06, 0.03, 2.4), noise=0.02, colour=(1.1, 1.0, 0.8))


def test_round_trip_keeps_values_dtypes_and_extra_columns(tmp_path):
    df = table()
    df["x"] = np.arange(len(df), dtype=float)
    p = write_samples(df, tmp_path / "s.parquet")
    back = read_samples(p)
    assert list(back.columns[:len(COLUMNS)]) == list(COLUMNS)
    for c in COLUMNS:
        np.testing.assert_array_equal(back[c].to_numpy(), df[c].to_numpy())
    assert back["u"].dtype == np.int32 and back["theta_in"].dtype == np.float64
    np.testing.assert_array_equal(back["x"], df["x"])
    assert pq.read_schema(p).metadata[b"glossrig.format"] == b"glossrig-samples/1"


def test_ward_samples_are_the_model_at_the_given_angles():
    df = table(200)
    p = WardParams(0.05, 0.01, 0.06, 0.03, 2.4)
    f = ward_from_angles(df["theta_in"], df["theta_out"], df["theta_h"], df["phi_h"], p)
    rel = df["g"] / f - 1
    assert abs(rel.mean()) < 0.005 and 0.012 < rel.std() < 0.028      # 2 % multiplicative noise
    np.testing.assert_allclose((df["r"] / df["g"]).median(), 1.1, rtol=0.02)


def test_luminance_is_rec709():
    assert luminance(1, 1, 1) == pytest.approx(1.0)
    assert luminance(1, 0, 0) == pytest.approx(0.2126)
    assert luminance(0, 1, 0) == pytest.approx(0.7152)
    assert luminance(0, 0, 1) == pytest.approx(0.0722)


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d.drop(columns=["g", "weight"]), "missing column.*g, weight"),
    (lambda d: d.iloc[:0], "empty"),
    (lambda d: d.assign(**{c: np.where(np.arange(len(d)) == 7, np.nan, d[c]) for c in "rgb"}),
     "no valid colour channel.*row 7"),
    (lambda d: d.assign(g=np.where(np.arange(len(d)) == 5, np.inf, d["g"])), "'g'.*infinite.*row 5"),
    (lambda d: d.assign(weight_b=np.where(np.arange(len(d)) == 3, -1.0, 1.0)), "'weight_b'.*row 3"),
    (lambda d: d.assign(phi_h=np.where(np.arange(len(d)) == 2, np.inf, d["phi_h"])), "'phi_h'.*infinite"),
    (lambda d: d.assign(theta_in=np.where(np.arange(len(d)) == 4, math.pi / 2, d["theta_in"])),
     r"'theta_in' outside \[0, pi/2\).*row 4"),
    (lambda d: d.assign(phi_out=d["phi_out"] + 7.0), r"'phi_out' outside \[0, 2 pi\]"),
    (lambda d: d.assign(theta_d=-d["theta_d"] - 0.1), "'theta_d' outside"),
    (lambda d: d.assign(weight=-1.0), "'weight' must be >= 0"),
    (lambda d: d.assign(weight=0.0), "zero in every row"),
    (lambda d: d.assign(b="bright"), "'b' must be numeric"),
    (lambda d: d.assign(u=d["u"] + 0.5), "'u' must hold whole numbers"),
    (lambda d: d.assign(led=-d["led"]), "'led' must be >= 0"),
    (lambda d: d.assign(rotation=720.0), "'rotation' outside"),
])
def test_bad_tables_are_refused_naming_file_and_column(tmp_path, mutate, message):
    bad = mutate(table())
    path = tmp_path / "bad.parquet"
    with pytest.raises(InputError, match=message) as e:
        write_samples(bad, path)
    assert str(path) in str(e.value)
    assert not path.exists()
    # the same table written without validation is refused by the reader
    bad.to_parquet(path)
    with pytest.raises(InputError, match=message) as e:
        read_samples(path)
    assert str(path) in str(e.value)


def test_negative_values_are_allowed_as_noise():
    df = table()
    df.loc[3, "b"] = -1e-4
    assert validate_samples(df)["b"].iloc[3] == -1e-4


def test_float_pixel_columns_holding_whole_numbers_are_accepted():
    df = table()
    df["u"] = df["u"].astype(float)
    assert validate_samples(df)["u"].dtype == np.int32


def test_unreadable_and_missing_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_samples(tmp_path / "nope.parquet")
    junk = tmp_path / "junk.parquet"
    junk.write_text("theta_in,phi_in\n0.1,0.2\n")
    with pytest.raises(InputError, match="not a readable Parquet") as e:
        read_samples(junk)
    assert str(junk) in str(e.value)
    with pytest.raises(InputError, match="directory"):
        read_samples(tmp_path)


def test_failed_write_leaves_the_existing_file_untouched(tmp_path):
    path = write_samples(table(), tmp_path / "s.parquet")
    before = path.read_bytes()
    with pytest.raises(InputError):
        write_samples(table().iloc[:0], path)
    assert path.read_bytes() == before
    with pytest.raises(InputError, match="refusing to overwrite"):
        write_samples(table(), path, overwrite=False)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["s.parquet"]     # no temporary left behind
