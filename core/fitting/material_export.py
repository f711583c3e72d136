"""The fitted material and its samples as files other tools open (issue 17, "Exports").

:func:`write_exports` writes, from a fit (:class:`~glossrig.core.fitting.fit.MaterialFit` or the
``fit.json`` it was saved as, read with :func:`glossrig.core.fitting.export.read_fit_json`) and
its samples table:

``material.xml``
    a Mitsuba 3 XML scene file holding one ``<bsdf type="glossrig_ward" id="material">``:
    :func:`glossrig.core.fitting.export.mitsuba_material`'s dict serialised to XML
    (:func:`mitsuba_xml`), so both carry the same parameters by construction. Loading
    it needs the project's plugin registered (``glossrig.twin.ward_bsdf.register()``).
``material_stock.xml``
    the closest material built from stock Mitsuba 3 plugins only
    (``id="material_stock"``): a ``blendbsdf`` of ``diffuse`` and an anisotropic
    ``roughconductor``, its parameters fitted to the samples
    (:func:`glossrig.core.models.stock_bsdf.fit_stock`; the choice of plugins, and what to do
    for a rotated lobe, are argued there). Its header states its residual beside the
    Ward fit's on the same samples and weights.
``material.brdf``
    a Disney BRDF Explorer analytic BRDF (Burley, "BRDF Explorer", Walt Disney
    Animation Studios, 2012; the format of its ``src/brdfs/*.brdf``: an ``analytic``
    line, ``::begin parameters`` with ``float NAME MIN MAX DEFAULT`` and ``color NAME R G
    B`` lines, ``::begin shader`` with GLSL defining ``vec3 BRDF(vec3 L, vec3 V, vec3 N,
    vec3 X, vec3 Y)``) implementing the extended Ward model exactly as
    :func:`glossrig.core.models.ward.ward_local` (thesis eq. 4.79-4.80, Ward's original
    ``1 / sqrt(cos th_i cos th_o)`` normalisation, the lobe rotation added to phi_h),
    the fitted values as defaults.
``samples.csv`` and ``samples.csv.json``
    every column of the samples table, a header line, floats written as the shortest
    decimal that reads back to the same double, so ``pandas.read_csv`` returns the same
    values; the sidecar JSON gives
    every column's dtype, unit and meaning, and the table's provenance.
    :func:`read_samples_csv` applies the sidecar's dtypes, returning a frame equal to
    the Parquet table's.

Mitsuba scene files: every file is a complete ``<scene version="3.0.0">`` holding the
named ``<bsdf>``, the form Mitsuba's ``<include filename="..."/>`` requires; a scene uses
it by ``<include filename="exports/material.xml"/>`` and ``<ref id="material"/>`` in a
shape. Knows nothing of Mitsuba itself (core imports neither twin nor Mitsuba).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from glossrig.core.errors import InputError

MATERIAL_XML = "material.xml"
STOCK_XML = "material_stock.xml"
BRDF_FILE = "material.brdf"
SAMPLES_CSV = "samples.csv"
SAMPLES_CSV_SIDECAR = "samples.csv.json"
STOCK_JSON = "material_stock.json"
CSV_FORMAT = "glossrig-samples-csv/1"

#: Mitsuba object tag of each plugin type these exports emit (Mitsuba 3 XML: the tag
#: names the object's class; ``<rgb>``, ``<float>``, ... are properties).
_OBJECT_TAGS = {"glossrig_ward": "bsdf", "diffuse": "bsdf", "roughconductor": "bsdf", "blendbsdf": "bsdf",
                "roughplastic": "bsdf", "principled": "bsdf", "conductor": "bsdf", "plastic": "bsdf",
                "twosided": "bsdf", "bitmap": "texture", "checkerboard": "texture"}
#: The stock plugins ``material_stock.xml`` is made of.
STOCK_PLUGINS = ("blendbsdf", "diffuse", "roughconductor")

# Units and meaning of the samples table's columns (glossrig.core.samples).
_COLUMN_DOC = {
    "theta_in": ("radian", "zenith of the light direction, tangent frame of thesis 4.3.5"),
    "phi_in": ("radian", "azimuth of the light direction from the tangent, counter-clockwise"),
    "theta_out": ("radian", "zenith of the camera direction"),
    "phi_out": ("radian", "azimuth of the camera direction"),
    "theta_h": ("radian", "zenith of the half vector"),
    "phi_h": ("radian", "azimuth of the half vector"),
    "theta_d": ("radian", "Rusinkiewicz difference angle theta_d"),
    "phi_d": ("radian", "Rusinkiewicz difference angle phi_d"),
    "r": ("1/sr", "BRDF value, red channel (thesis eq. 4.78); empty (NaN): missing, out of dynamic range"),
    "g": ("1/sr", "BRDF value, green channel; empty (NaN): missing"),
    "b": ("1/sr", "BRDF value, blue channel; empty (NaN): missing"),
    "weight": ("1", "relative statistical weight, proportional to 1 / variance"),
    "weight_r": ("1", "statistical weight of r alone, on the scale of weight; empty where r is missing"),
    "weight_g": ("1", "statistical weight of g alone, on the scale of weight; empty where g is missing"),
    "weight_b": ("1", "statistical weight of b alone, on the scale of weight; empty where b is missing"),
    "u": ("pixel", "image column"),
    "v": ("pixel", "image row"),
    "led": ("id", "LED id of the rig description"),
    "rotation": ("degree", "sample rotation (thesis eq. 4.62)"),
    "x": ("mm", "surface point, holder frame"),
    "y": ("mm", "surface point, holder frame"),
    "z": ("mm", "surface point, holder frame"),
}


# ----------------------------------------------------------------------------
# Mitsuba XML
# ----------------------------------------------------------------------------

def _num(v: float) -> str:
    v = float(v)
    if not math.isfinite(v):
        raise InputError(f"cannot export a non-finite value {v!r} to a Mitsuba scene")
    return repr(v)


def _comment(text: str, indent: str = "") -> str:
    """An XML comment (``--`` is not allowed inside one)."""
    body = text.replace("--", "- -").rstrip()
    return f"{indent}<!--\n" + "\n".join(f"{indent}  {ln}".rstrip() for ln in body.splitlines()) + f"\n{indent}-->\n"


def _xml_object(d: dict, indent: str, name: str | None = None, id: str | None = None) -> str:
    kind: Any = d.get("type")
    tag = _OBJECT_TAGS.get(kind)
    if tag is None:
        raise ValueError(f"no Mitsuba object tag known for plugin type {kind!r}")
    attrs = f"type={quoteattr(kind)}"
    if id is not None:
        attrs += f" id={quoteattr(id)}"
    if name is not None:
        attrs += f" name={quoteattr(name)}"
    lines = [f"{indent}<{tag} {attrs}>\n"]
    inner = indent + "    "
    for k, v in d.items():
        if k == "type":
            continue
        if isinstance(v, dict) and v.get("type") == "rgb":
            vals = v["value"]
            vals = [vals] * 3 if isinstance(vals, (int, float)) else list(vals)
            if len(vals) != 3:
                raise ValueError(f"rgb property {k!r} must hold 3 values")
            lines.append(f'{inner}<rgb name={quoteattr(k)} value="{", ".join(_num(x) for x in vals)}"/>\n')
        elif isinstance(v, dict):
            lines.append(_xml_object(v, inner, name=k))
        elif isinstance(v, bool):
            lines.append(f'{inner}<boolean name={quoteattr(k)} value="{"true" if v else "false"}"/>\n')
        elif isinstance(v, int):
            lines.append(f'{inner}<integer name={quoteattr(k)} value="{v}"/>\n')
        elif isinstance(v, float):
            lines.append(f'{inner}<float name={quoteattr(k)} value="{_num(v)}"/>\n')
        elif isinstance(v, str):
            lines.append(f"{inner}<string name={quoteattr(k)} value={quoteattr(v)}/>\n")
        else:
            raise ValueError(f"cannot write property {k!r} of type {type(v).__name__} to Mitsuba XML")
    lines.append(f"{indent}</{tag}>\n")
    return "".join(lines)


def mitsuba_xml(material: dict, id: str, comment: str | None = None) -> str:
    """A Mitsuba 3 XML scene file holding ``material`` (a ``mi.load_dict`` dictionary:
    a plugin ``type``, properties as floats, ints, bools, strings, ``{"type": "rgb",
    "value": [r, g, b]}``, nested plugins as dicts whose key becomes the ``name``
    attribute) as one top-level object with the given ``id``. Floats are written with
    ``repr`` so the XML and the dict give Mitsuba the same doubles."""
    out = ['<?xml version="1.0" encoding="utf-8"?>\n']
    if comment:
        out.append(_comment(comment))
    out.append('<scene version="3.0.0">\n')
    out.append(_xml_object(material, "    ", id=id))
    out.append("</scene>\n")
    return "".join(out)


def stock_material(stock) -> dict:
    """The ``mi.load_dict`` dictionary of a :class:`~glossrig.core.models.stock_bsdf.StockFit`:
    ``blendbsdf`` (weight ``w``) of ``diffuse`` (``bsdf_0``) and ``roughconductor``
    (``bsdf_1``, ``material="none"``: Fresnel reflectance 1, scaled by a constant
    ``specular_reflectance``), see :meth:`StockFit.blend`. ``alpha_u`` lies along the
    shape's ``dp/du``: the lobe rotation is not in the material (see
    :mod:`glossrig.core.models.stock_bsdf`)."""
    bl = stock.blend()
    p = stock.params
    return {"type": "blendbsdf", "weight": float(bl["weight"]),
            "bsdf_0": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(x) for x in bl["R"]]}},
            "bsdf_1": {"type": "roughconductor", "material": "none", "distribution": p.distribution,
                       "alpha_u": float(p.alpha_u), "alpha_v": float(p.alpha_v),
                       "specular_reflectance": {"type": "rgb", "value": [float(x) for x in bl["S"]]}}}


# ----------------------------------------------------------------------------
# Disney BRDF Explorer
# ----------------------------------------------------------------------------

_BRDF_SHADER = """\
vec3 BRDF( vec3 L, vec3 V, vec3 N, vec3 X, vec3 Y )
{
    float PI = 3.14159265358979323846;
    float cos_in = dot(L, N);
    float cos_out = dot(V, N);
    if (cos_in <= 0.0 || cos_out <= 0.0) return vec3(0.0);
    vec3 H = normalize(L + V);
    float hx = dot(H, X);
    float hy = dot(H, Y);
    float hz = dot(H, N);
    float c = cos(lobe_rotation);
    float s = sin(lobe_rotation);
    float hu = c * hx - s * hy;
    float hv = s * hx + c * hy;
    float expo = -((hu / alpha_x) * (hu / alpha_x) + (hv / alpha_y) * (hv / alpha_y)) / (hz * hz);
    float spec = exp(expo) / (4.0 * PI * alpha_x * alpha_y * sqrt(cos_in * cos_out));
    return rho_d / PI + rho_s * spec;
}
"""


def brdf_explorer(material: dict, comment: str | None = None) -> str:
    """A BRDF Explorer ``.brdf`` analytic file of a ``glossrig_ward`` material dict
    (:func:`glossrig.core.fitting.export.mitsuba_material`): colour parameters ``rho_d``,
    ``rho_s``, float parameters ``alpha_x``, ``alpha_y`` (range (1e-4, 0.5] of the fit,
    thesis Table 4.2) and ``lobe_rotation`` (radians, [0, pi]), the material's values as
    defaults (written with ``repr``). The shader is eq. 4.79-4.80 as
    :func:`glossrig.core.models.ward.ward_local` computes it: ``hu, hv`` are the half vector's
    coordinates along the lobe axes (the tangent ``X`` turned by ``-lobe_rotation``), so
    ``tan^2 th_h cos^2 a_n = hu^2 / hz^2``. BRDF Explorer's ``X, Y, N`` (tangent,
    bitangent, normal; right-handed) are the tangent frame of thesis 4.3.5."""
    if material.get("type") != "glossrig_ward":
        raise ValueError(f"expected a glossrig_ward material, got {material.get('type')!r}")
    rd, rs = material["rho_d"]["value"], material["rho_s"]["value"]
    ax, ay, rot = (float(material[k]) for k in ("alpha_x", "alpha_y", "lobe_rotation"))
    lines = ["analytic", ""]
    for ln in (comment or "").splitlines():
        lines.append(f"# {ln}".rstrip())
    lines += ["", "# [type] [name] [min val] [max val] [default val]; color: [name] [r] [g] [b]",
              "::begin parameters",
              "color rho_d " + " ".join(_num(x) for x in rd),
              "color rho_s " + " ".join(_num(x) for x in rs)]
    for name, v, lo, hi in (("alpha_x", ax, 1e-4, 0.5), ("alpha_y", ay, 1e-4, 0.5),
                            ("lobe_rotation", rot, 0.0, math.pi)):
        lines.append(f"float {name} {_num(min(lo, v))} {_num(max(hi, v))} {_num(v)}")
    lines += ["::end parameters", "", "::begin shader", "", _BRDF_SHADER.rstrip("\n"), "", "::end shader", ""]
    return "\n".join(lines)


# ----------------------------------------------------------------------------
# Samples as CSV
# ----------------------------------------------------------------------------

def samples_csv_sidecar(df) -> dict:
    """The sidecar of ``samples.csv``: per column its dtype, unit and meaning, how to read
    the file back, and the table's provenance (``df.attrs["provenance"]``)."""
    cols = []
    for c in df.columns:
        unit, meaning = _COLUMN_DOC.get(str(c), (None, None))
        cols.append({"name": str(c), "dtype": str(df[c].dtype), "unit": unit, "meaning": meaning})
    return {"format": CSV_FORMAT, "file": SAMPLES_CSV, "columns": cols,
            "read_with": "pandas.read_csv(path, dtype={name: dtype}) or glossrig.core.fitting.material_export.read_samples_csv",
            "float_format": "shortest decimal that reads back to the same float64",
            "provenance": df.attrs.get("provenance")}


def samples_csv_bytes(df) -> bytes:
    """``df`` as CSV: a header line, no index, floats as the shortest decimal that reads
    back to the same double (Arrow's CSV writer: about 8x faster than pandas' ``to_csv``,
    which writes the same shortest form)."""
    import pyarrow as pa
    import pyarrow.csv as pcsv

    table = pa.Table.from_pandas(df, preserve_index=False)
    buf = pa.BufferOutputStream()
    pcsv.write_csv(table, buf, pcsv.WriteOptions(include_header=True))
    return buf.getvalue().to_pybytes()


def read_samples_csv(path: str | Path):
    """Read a ``samples.csv`` with the dtypes its sidecar ``samples.csv.json`` records (the
    one reader of both files; errors name the file)."""
    import pandas as pd

    from glossrig.core.toml_input import read_json

    path = Path(path)
    side = path.with_name(path.name + ".json")
    if not side.exists():
        raise InputError("sidecar not found (it records the columns' dtypes)", path=side)
    meta = read_json(side, "samples.csv sidecar")
    try:
        dtypes = {c["name"]: c["dtype"] for c in meta["columns"]}
    except (KeyError, TypeError) as e:
        raise InputError(f"not a samples.csv sidecar ({e})", path=side) from None
    try:
        df = pd.read_csv(path, dtype=dtypes)
    except FileNotFoundError:
        raise InputError("samples CSV not found", path=path) from None
    except (OSError, ValueError, pd.errors.ParserError) as e:
        raise InputError(f"not a readable samples CSV ({e})", path=path) from None
    if list(df.columns) != list(dtypes):
        raise InputError(f"columns {list(df.columns)} differ from the sidecar's {list(dtypes)}", path=path)
    return df


# ----------------------------------------------------------------------------
# All exports
# ----------------------------------------------------------------------------

def _load_fit(fit):
    from glossrig.core.fitting.export import read_fit_json

    if isinstance(fit, (str, Path)):
        return read_fit_json(fit), str(fit)
    return fit, fit.source


def _fit_options(material_fit) -> tuple[str, bool, float | None]:
    opts = material_fit.options or {}
    lum = material_fit.fits.get("luminance") or next(iter(material_fit.fits.values()))
    weighting = opts.get("weighting", lum.weighting)
    return weighting, bool(opts.get("use_weight_column", True)), opts.get("clip", lum.clip)


def _fmt(v) -> str:
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def write_exports(fit, samples_df, out_dir: str | Path) -> list[Path]:
    """Write ``material.xml``, ``material_stock.xml`` (+ ``material_stock.json``, the stock
    fit and both residuals), ``material.brdf``, ``samples.csv`` (+ ``samples.csv.json``)
    into ``out_dir`` (created when missing; its parent must exist). ``fit``: a
    :class:`~glossrig.core.fitting.fit.MaterialFit` or the path of its ``fit.json``;
    ``samples_df``: the samples table the fit was made from (:mod:`glossrig.core.samples`).
    Each file is written atomically. Returns the paths written, in that order.

    The measure verb calls it with ``DIR / "exports"``."""
    from glossrig.core.atomic import atomic_write_bytes, atomic_write_json
    from glossrig.core.fitting.export import mitsuba_material
    from glossrig.core.models.stock_bsdf import fit_stock

    mf, source = _load_fit(fit)
    out = Path(out_dir)
    if not out.parent.is_dir():
        raise InputError("parent folder of the exports folder does not exist", path=out)
    out.mkdir(exist_ok=True)
    material = mitsuba_material(mf)
    src = f"fit: {source}" if source else "fit: (in memory)"

    # The project's plugin.
    p = _ward_luminance(mf)
    head = (f"glossrig: the fitted extended Ward material (thesis eq. 4.79-4.80), plugin 'glossrig_ward'.\n"
            f"{src}\n"
            f"Register the plugin before loading: glossrig.twin.ward_bsdf.register()\n"
            f"Use: <include filename=\"{MATERIAL_XML}\"/> and <ref id=\"material\"/> in a shape.\n"
            f"Lobe: one for all channels (the {material_fit_lobe(mf)} fit's), rho_d / rho_s per channel (r, g, b).\n"
            f"alpha_x runs along the shading frame's s = dp/du turned by -lobe_rotation (radians) about n.\n"
            f"Luminance: rho_d={p.rho_d:.6g} rho_s={p.rho_s:.6g} alpha_x={p.alpha_x:.6g} "
            f"alpha_y={p.alpha_y:.6g} lobe_rotation={p.lobe_rotation:.6g} rad")
    paths = []
    path = out / MATERIAL_XML
    atomic_write_bytes(path, mitsuba_xml(material, "material", head).encode())
    paths.append(path)

    # The stock approximation, fitted to the samples.
    weighting, use_w, clip = _fit_options(mf)
    stock = fit_stock(samples_df, p, weighting=weighting, use_weight_column=use_w, clip=clip)
    sp, rs, rw = stock.params, stock.residuals, stock.ward_residuals
    rot_deg = math.degrees(sp.rotation)
    head = (f"glossrig: the closest stock Mitsuba 3 material to the fitted extended Ward model:\n"
            f"blendbsdf(diffuse, roughconductor material=none, {sp.distribution}), "
            f"fitted to {stock.n_samples} samples\n"
            f"(weighted least squares of thesis eq. 4.81-4.82, luminance; see glossrig.core.models.stock_bsdf).\n"
            f"{src}\n"
            f"Stock plugins only. Use: <include filename=\"{STOCK_XML}\"/> and <ref id=\"material_stock\"/>.\n"
            f"Weighted RMSE (1/sr): stock {_fmt(rs['weighted_rmse'])}, Ward {_fmt(rw['weighted_rmse'])}; "
            f"median |relative error|: stock {_fmt(rs['median_abs_relative'])}, "
            f"Ward {_fmt(rw['median_abs_relative'])}.\n"
            f"Lobe: alpha_u={sp.alpha_u:.6g} alpha_v={sp.alpha_v:.6g}, rotation {sp.rotation:.6g} rad "
            f"({rot_deg:.4g} deg).\n"
            f"alpha_u runs along the shape's dp/du and no stock plugin can turn it. For the measured lobe,\n"
            f"dp/du must run along the sample's tangent turned by -{rot_deg:.4g} deg about the normal:\n"
            f"rotate the shape's uv coordinates by that angle (a rectangle or disk: prepend\n"
            f"<rotate z=\"1\" angle=\"{-rot_deg:.6g}\"/> to its to_world). Nothing to do when the angle is 0 or 180.")
    path = out / STOCK_XML
    atomic_write_bytes(path, mitsuba_xml(stock_material(stock), "material_stock", head).encode())
    paths.append(path)
    path = out / STOCK_JSON
    doc = stock.to_json()
    doc["source"] = source
    doc["mitsuba"] = stock_material(stock)          # what material_stock.xml holds, as a mi.load_dict dict
    atomic_write_json(path, doc, indent=2, allow_nan=False, default=_json_default)
    paths.append(path)

    # BRDF Explorer.
    head = (f"glossrig: the fitted extended Ward BRDF (thesis eq. 4.79-4.80; Ward 1992 with a lobe rotation).\n"
            f"{src}\n"
            f"rho_d, rho_s: per channel for one lobe; alpha_x along the tangent X turned by -lobe_rotation "
            f"(radians) about N.\n"
            f"Normalisation 1 / (4 pi alpha_x alpha_y sqrt(cos_in cos_out)) as the thesis (not Walter 2005's).")
    path = out / BRDF_FILE
    atomic_write_bytes(path, brdf_explorer(material, head).encode())
    paths.append(path)

    # Samples.
    path = out / SAMPLES_CSV
    atomic_write_bytes(path, samples_csv_bytes(samples_df))
    paths.append(path)
    path = out / SAMPLES_CSV_SIDECAR
    side = samples_csv_sidecar(samples_df)
    atomic_write_json(path, side, indent=2, default=_json_default)
    paths.append(path)
    return paths


def _ward_luminance(mf):
    """The Ward parameters of the fit's luminance: the luminance channel's fit, or, for a
    fit without one, the shared lobe with the Rec. 709 luminance of its RGB albedos (the
    albedos enter eq. 4.79 linearly, so the luminance of the RGB model is that Ward model)."""
    from glossrig.core.samples import luminance
    from glossrig.core.models.ward import WardParams

    if "luminance" in mf.fits:
        return mf.fits["luminance"].params
    s = mf.shared_rgb
    return WardParams(rho_d=float(luminance(*s["rho_d"])), rho_s=float(luminance(*s["rho_s"])),
                      alpha_x=float(s["alpha_x"]), alpha_y=float(s["alpha_y"]),
                      lobe_rotation=float(s["lobe_rotation"]))


def material_fit_lobe(mf) -> str:
    """Which channel's fit gave the shared lobe of a MaterialFit."""
    return str((mf.shared_rgb or {}).get("lobe_from", "luminance"))


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
