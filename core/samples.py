"""The BRDF samples table (design.md "Data contracts"): one row per pixel x light x rotation.

A Parquet file with these columns (extra columns are kept and not checked):

==========================  ========  ==================================================
column                      dtype     meaning
==========================  ========  ==================================================
theta_in, theta_out         float64   zenith of the light / camera direction, [0, pi/2)
phi_in, phi_out             float64   azimuth from the tangent, counter-clockwise, [0, 2 pi)
theta_h, phi_h              float64   half vector (thesis 4.3.5, eq. 4.64-4.72 corrected
                                      in :mod:`glossrig.core.models.angles`)
theta_d, phi_d              float64   Rusinkiewicz difference angles (EGWR 1998)
r, g, b                     float64   BRDF value per colour channel, 1/sr (thesis eq. 4.78);
                                      NaN = that channel is missing for the row (below)
weight                      float64   relative statistical weight of the row, >= 0; taken
                                      as proportional to 1 / variance of its BRDF value
                                      (1 everywhere when unknown; 0 drops the row)
u, v                        int32     pixel column and row
led                         int32     LED id of the rig description
rotation                    float64   sample rotation, degrees (thesis eq. 4.62)
==========================  ========  ==================================================

Angles are radians in the local tangent frame of thesis 4.3.5 (x = tangent,
y = bitangent, z = normal). BRDF values must be finite but may be slightly
negative: after black-level subtraction the noise of dark pixels is zero-mean,
and dropping or clamping the negative values would bias the diffuse level.
Both directions must lie strictly above the surface (theta < pi/2).

**Missing channels (per-channel validity).** A colour channel that has no valid HDR
value for a row - too dark even at the longest exposure, saturated even at the
shortest (:data:`glossrig.core.radiometry.hdr.STATUS_REASONS`), in the sample or in the
reference capture - is NaN in that row; the row keeps its other channels. A missing
channel is never a reason to drop the others: a strongly coloured material has one
channel below the noise over most of the sample, and dropping whole rows would keep only
the highlight (issue 14). So: ``r, g, b`` are finite or NaN (never infinite), and every
row has at least one finite channel. :func:`valid_channels` gives the mask. Whoever
reads the table uses each channel on its finite rows only (``glossrig fit``:
:func:`glossrig.core.fitting.fit.fit_samples`, which also says how luminance is formed
where a channel is missing); ``np.nanmean`` and the like, not ``mean``.

Optional per-channel weights ``weight_r, weight_g, weight_b`` (float64, >= 0; NaN where
the channel is missing), written by ``glossrig extract``: the inverse variance of that
channel's value, on the scale of ``weight`` (which is their mean over the row's valid
channels). A fit of one channel uses its own (:func:`channel_weight`); tables without
them use ``weight`` for every channel.

:func:`read_samples` and :func:`write_samples` check columns, dtypes, NaN/inf
and ranges, and every error names the file and the column.
"""
from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pandas as pd

from glossrig.core.models.angles import ANGLE_COLUMNS
from glossrig.core.errors import InputError

FORMAT = "glossrig-samples/1"
VALUE_COLUMNS = ("r", "g", "b")
FLOAT_COLUMNS = ANGLE_COLUMNS + VALUE_COLUMNS + ("weight", "rotation")
INT_COLUMNS = ("u", "v", "led")
COLUMNS = ANGLE_COLUMNS + VALUE_COLUMNS + ("weight", "u", "v", "led", "rotation")
#: optional per-channel weights (module docstring), in the order of VALUE_COLUMNS
CHANNEL_WEIGHT_COLUMNS = tuple(f"weight_{c}" for c in VALUE_COLUMNS)
# Rec. ITU-R BT.709 / sRGB luminance weights (linear RGB).
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)

_EPS = 1e-9
_RANGES = {
    "theta_in": (0.0, math.pi / 2, "[0, pi/2)"),
    "theta_out": (0.0, math.pi / 2, "[0, pi/2)"),
    "theta_h": (0.0, math.pi / 2, "[0, pi/2)"),
    "theta_d": (0.0, math.pi / 2, "[0, pi/2]"),
    "phi_in": (0.0, 2 * math.pi, "[0, 2 pi]"),
    "phi_out": (0.0, 2 * math.pi, "[0, 2 pi]"),
    "phi_h": (0.0, 2 * math.pi, "[0, 2 pi]"),
    "phi_d": (0.0, 2 * math.pi, "[0, 2 pi]"),
    "rotation": (-360.0, 360.0, "[-360, 360] degrees"),
}
_STRICT_UPPER = ("theta_in", "theta_out", "theta_h")


def luminance(r, g, b) -> np.ndarray:
    """Rec. 709 / sRGB relative luminance ``Y = 0.2126 r + 0.7152 g + 0.0722 b``
    of linear RGB values (ITU-R BT.709-6, item 3.2; IEC 61966-2-1)."""
    wr, wg, wb = LUMINANCE_WEIGHTS
    return wr * np.asarray(r, np.float64) + wg * np.asarray(g, np.float64) + wb * np.asarray(b, np.float64)


def valid_channels(df) -> np.ndarray:
    """(n, 3) bool: which of ``r, g, b`` each row has (finite; NaN = missing, see the
    module docstring)."""
    return np.isfinite(np.stack([np.asarray(df[c], np.float64) for c in VALUE_COLUMNS], axis=1))


def channel_weight(df, channel: str) -> np.ndarray:
    """The statistical weight of ``channel``'s values (``r``, ``g`` or ``b``): its own
    ``weight_<channel>`` column where the table has one, else ``weight``; 0 where the
    channel is missing, so that a fit of it can simply drop the zero-weight rows."""
    col = f"weight_{channel}"
    w = np.asarray(df[col] if col in df else df["weight"], np.float64)
    ok = np.isfinite(np.asarray(df[channel], np.float64)) & np.isfinite(w)
    return np.where(ok, w, 0.0)


def _first_bad(mask: np.ndarray) -> str:
    idx = np.flatnonzero(mask)
    return f"{idx.size} row(s), first at row {idx[0]}"


def validate_samples(df: pd.DataFrame, source: str | Path | None = None) -> pd.DataFrame:
    """Check a samples table and return it with the canonical dtypes (a new frame).

    ``source`` names the file (or object) in every error message."""
    where = "samples table" if source is None else None
    src = None if source is None else str(source)

    def fail(msg):
        raise InputError(msg if src else f"{where}: {msg}", path=src)

    if not isinstance(df, pd.DataFrame):
        fail(f"expected a table, got {type(df).__name__}")
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        fail(f"missing column(s) {', '.join(missing)} (a samples table needs {', '.join(COLUMNS)})")
    if len(df) == 0:
        fail("the samples table is empty (no rows)")
    out = {}
    for c in FLOAT_COLUMNS:
        s = df[c]
        if not (pd.api.types.is_float_dtype(s.dtype) or pd.api.types.is_integer_dtype(s.dtype)) \
                or pd.api.types.is_bool_dtype(s.dtype):
            fail(f"column {c!r} must be numeric (float), got dtype {s.dtype}")
        a = s.to_numpy(dtype=np.float64, na_value=np.nan)
        if c in VALUE_COLUMNS:          # NaN: the channel is missing in that row (module docstring)
            bad = np.isinf(a)
            if bad.any():
                fail(f"column {c!r} holds infinite values: {_first_bad(bad)} (a missing channel is NaN)")
        else:
            bad = ~np.isfinite(a)
            if bad.any():
                fail(f"column {c!r} holds NaN or infinite values: {_first_bad(bad)}")
        out[c] = a
    none = ~np.isfinite(np.stack([out[c] for c in VALUE_COLUMNS], axis=1)).any(axis=1)
    if none.any():
        fail(f"rows with no valid colour channel (r, g and b all NaN): {_first_bad(none)}; a row needs at least "
             f"one channel")
    for c, wc in zip(VALUE_COLUMNS, CHANNEL_WEIGHT_COLUMNS):
        if wc in df.columns:
            a = pd.to_numeric(df[wc], errors="coerce").to_numpy(dtype=np.float64, na_value=np.nan)
            bad = np.isfinite(out[c]) & ~(np.isfinite(a) & (a >= 0))
            if bad.any():
                fail(f"column {wc!r} must be a finite weight >= 0 where {c!r} is valid: {_first_bad(bad)}")
    for c in INT_COLUMNS:
        s = df[c]
        if pd.api.types.is_bool_dtype(s.dtype):
            fail(f"column {c!r} must be integer, got dtype {s.dtype}")
        if pd.api.types.is_integer_dtype(s.dtype):
            if s.isna().any():
                fail(f"column {c!r} holds missing values: {_first_bad(s.isna().to_numpy())}")
            a = s.to_numpy(dtype=np.int64)
        elif pd.api.types.is_float_dtype(s.dtype):
            f = s.to_numpy(dtype=np.float64, na_value=np.nan)
            bad = ~np.isfinite(f) | (f != np.round(f))
            if bad.any():
                fail(f"column {c!r} must hold whole numbers: {_first_bad(bad)}")
            a = f.astype(np.int64)
        else:
            fail(f"column {c!r} must be integer, got dtype {s.dtype}")
        if (a < 0).any():
            fail(f"column {c!r} must be >= 0: {_first_bad(a < 0)}")
        if (a > np.iinfo(np.int32).max).any():
            fail(f"column {c!r} exceeds the int32 range")
        out[c] = a.astype(np.int32)
    for c, (lo, hi, text) in _RANGES.items():
        a = out[c]
        bad = (a < lo - _EPS) | ((a >= hi) if c in _STRICT_UPPER else (a > hi + _EPS))
        if bad.any():
            fail(f"column {c!r} outside {text}: {_first_bad(bad)} (value {a[np.flatnonzero(bad)[0]]!r})")
    w = out["weight"]
    if (w < 0).any():
        fail(f"column 'weight' must be >= 0: {_first_bad(w < 0)}")
    if not (w > 0).any():
        fail("column 'weight' is zero in every row: nothing to fit")
    res = pd.DataFrame({c: out[c] for c in COLUMNS})
    for c in df.columns:
        if c not in res.columns:
            res[c] = df[c].to_numpy()
    return res


def read_samples(path: str | Path) -> pd.DataFrame:
    """Read and validate a samples Parquet file (see the module docstring)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    if not path.exists():
        raise InputError("samples file not found", path=path)
    if path.is_dir():
        raise InputError("is a directory, expected a samples Parquet file", path=path)
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError, ValueError) as e:
        raise InputError(f"not a readable Parquet file ({e})", path=path) from None
    try:
        df = table.to_pandas()
    except (pa.ArrowException, ValueError, TypeError) as e:
        raise InputError(f"cannot convert the table ({e})", path=path) from None
    out = validate_samples(df, path)
    out.attrs["provenance"] = _provenance_of(table.schema.metadata, path)
    out.attrs["poses"] = _provenance_of(table.schema.metadata, path, POSES_KEY)
    return out


#: schema metadata key of the sample capture's solved poses (``glossrig extract``;
#: :func:`glossrig.core.extraction.extract.recorded_geometry`)
POSES_KEY = b"glossrig.poses"


def _provenance_of(meta: dict | None, path, key: bytes | None = None) -> dict | None:
    """The JSON under ``key`` (default: the provenance's) of a Parquet schema's metadata (None
    when not recorded)."""
    import json

    from glossrig.core.provenance import PARQUET_KEY

    raw = (meta or {}).get(key or PARQUET_KEY)
    if raw is None:
        return None
    try:
        return json.loads(raw)
    except (ValueError, UnicodeDecodeError) as e:
        what = "provenance" if key is None else key.decode()
        raise InputError(f"unreadable {what} in the schema metadata ({e})", path=path) from None


def read_provenance(path: str | Path) -> dict | None:
    """The provenance :func:`write_samples` recorded in a samples file (schema metadata
    ``glossrig.provenance``; see :mod:`glossrig.core.provenance`), without reading the rows.
    None for a table written without one."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    try:
        meta = pq.read_schema(path).metadata
    except (pa.ArrowException, OSError, ValueError) as e:
        raise InputError(f"not a readable Parquet file ({e})", path=path) from None
    return _provenance_of(meta, path)


def write_samples(df: pd.DataFrame, path: str | Path, *, overwrite: bool = True,
                  provenance: dict | None = None) -> Path:
    """Validate ``df`` and write it as Parquet (zstd), atomically: on any error
    nothing is written and an existing file is left untouched.

    The file's schema metadata records ``glossrig.format = glossrig-samples/1`` and,
    when given, ``glossrig.provenance`` = the JSON of ``provenance`` (what the table was
    made from: :func:`glossrig.core.provenance.provenance`; ``read_samples`` returns it
    as ``df.attrs["provenance"]``, :func:`read_provenance` alone), and where ``df.attrs``
    holds them the sample capture's solved poses under :data:`POSES_KEY` (``df.attrs["poses"]``
    when read back).
    With ``overwrite=False`` an existing file is an error."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from glossrig.core.atomic import atomic_write_bytes

    path = Path(path)
    if path.exists() and not overwrite:
        raise InputError("exists already; refusing to overwrite it", path=path)
    if not path.parent.is_dir():
        raise InputError("parent folder does not exist", path=path)
    clean = validate_samples(df, path)
    table = pa.Table.from_pandas(clean, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[b"glossrig.format"] = FORMAT.encode()
    meta[b"glossrig.angle_unit"] = b"radian"
    if provenance is not None:
        import json

        from glossrig.core.provenance import PARQUET_KEY

        meta[PARQUET_KEY] = json.dumps(provenance, sort_keys=True, allow_nan=False).encode()
    if df.attrs.get("poses"):
        import json

        meta[POSES_KEY] = json.dumps(df.attrs["poses"], sort_keys=True, allow_nan=False).encode()
    table = table.replace_schema_metadata(meta)
    buf = io.BytesIO()
    pq.write_table(table, buf, compression="zstd")
    atomic_write_bytes(path, buf.getvalue())
    return path


def ward_samples(geometry: pd.DataFrame, params, *, noise: float = 0.0, seed: int = 0,
                 colour=(1.0, 1.0, 1.0)) -> pd.DataFrame:
    """A samples table of a known extended-Ward material (eq. 4.79-4.80) at given angles.

    ``geometry``: a frame with the angle columns, ``u, v, led, rotation`` - e.g.
    :func:`glossrig.core.extraction.cylinder.nominal_samples`, the angles the rig measures.
    ``params``: one :class:`~glossrig.core.models.ward.WardParams` for all channels or
    a mapping ``{"r": .., "g": .., "b": ..}``; ``colour`` scales ``rho_d`` and
    ``rho_s`` of a single parameter set per channel. ``noise``: standard
    deviation of independent multiplicative Gaussian noise (``f * (1 + noise * N(0,1))``),
    roughly how shot noise and LED fluctuations act on HDR values. Weight 1.
    Ground truth for fitting tests and benchmarks; no rendering involved.
    """
    from dataclasses import replace

    from glossrig.core.models.ward import ward_from_angles

    if isinstance(params, dict):
        per = {c: params[c] for c in VALUE_COLUMNS}
    else:
        per = {c: replace(params, rho_d=params.rho_d * k, rho_s=params.rho_s * k)
               for c, k in zip(VALUE_COLUMNS, colour)}
    rng = np.random.default_rng(seed)
    out = pd.DataFrame({c: np.asarray(geometry[c], np.float64) for c in ANGLE_COLUMNS})
    for c in VALUE_COLUMNS:
        f = ward_from_angles(out["theta_in"], out["theta_out"], out["theta_h"], out["phi_h"], per[c])
        if noise:
            f = f * (1 + noise * rng.standard_normal(f.size))
        out[c] = f
    out["weight"] = 1.0
    out["u"] = np.asarray(geometry["u"], np.int32)
    out["v"] = np.asarray(geometry["v"], np.int32)
    out["led"] = np.asarray(geometry["led"], np.int32)
    out["rotation"] = np.asarray(geometry["rotation"], np.float64)
    return out
