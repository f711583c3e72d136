"""Material descriptions: what a sample is made of, as data.

A material spec (``glossrig simulate --material``) is one of
``ward:rho_d=..,rho_s=..,alpha_x=..,alpha_y=..,lobe_rotation=..`` (lobe_rotation in
radians, or with a unit: ``140deg``, ``2.44rad``; every value is range-checked by
:func:`glossrig.core.models.ward.check_physical`: rho_d in [0, 1], rho_s >= 0,
rho_d + rho_s <= 1, 0 < alpha <= 0.5 as in thesis Table 4.2, |lobe_rotation| <= 2 pi),
``rho_d`` and ``rho_s`` either one grey value or one per colour channel, ``R/G/B``
(``ward:rho_d=0.45/0.30/0.01,rho_s=0.05,...``; in a material file a list of three),
``lambert:ALBEDO``, ``measured:PATH`` (an RGL ``.bsdf`` file, Dupuy & Jakob 2018),
``mitsuba:FILE.xml`` (any stock Mitsuba 3 BSDF, e.g. an anisotropic ``roughconductor``,
as a ``<bsdf type=...>`` element; a bare name such as ``mitsuba:aniso_roughconductor_ggx``
is looked up in ``scenes/materials``; core reads the text, the twin loads it with
Mitsuba, :mod:`glossrig.twin.mitsuba_material`) or the name of a file in
``scenes/materials`` (the packaged scenes,
:func:`glossrig.core.resources.scenes_dir`, so the names work wherever glossrig is
installed and from any folder).

A coloured Ward material (per-channel albedos, one lobe) keeps the albedos in
:attr:`Material.rgb`; its :attr:`Material.ward` is then the material's luminance
(Rec. 709 Y of the albedos, :data:`glossrig.core.samples.LUMINANCE_WEIGHTS`), which is
exactly the Ward BRDF of its luminance, since eq. 4.79 is linear in rho_d and rho_s:
what a luminance fit recovers. Every channel is range-checked on its own.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from glossrig.core.errors import InputError
from glossrig.core.resources import scenes_dir
from glossrig.core.models.ward import WardParams, check_physical, parse_angle
from glossrig.core.toml_input import read_toml

#: the packaged material descriptions (one TOML file per name)
MATERIALS_DIR = scenes_dir() / "materials"


@dataclass(frozen=True)
class Material:
    kind: str                     # "ward" | "lambert" | "measured" | "mitsuba"
    label: str
    ward: WardParams | None = None
    albedo: float | None = None
    path: str | None = None
    rgb: dict | None = None       # coloured Ward: {"rho_d": (r, g, b), "rho_s": (r, g, b)}; ward = its luminance
    xml: str | None = None        # mitsuba: the text of the BSDF description (what the twin renders)

    def channel_ward(self, channel: str) -> WardParams:
        """The Ward parameters of colour channel ``r``, ``g`` or ``b`` (a grey material's
        for every channel)."""
        if self.ward is None:
            raise InputError(f"material {self.label!r} is not a Ward material")
        if self.rgb is None:
            return self.ward
        k = "rgb".index(channel)
        return replace(self.ward, rho_d=self.rgb["rho_d"][k], rho_s=self.rgb["rho_s"][k])

    def to_json(self) -> dict:
        d: dict[str, Any] = {"kind": self.kind, "label": self.label}
        if self.ward is not None:
            d["ward"] = self.ward.as_dict()
        if self.rgb is not None:
            d["ward_rgb"] = {c: self.channel_ward(c).as_dict() for c in "rgb"}
        if self.albedo is not None:
            d["albedo"] = self.albedo
        if self.path is not None:
            d["path"] = self.path
        if self.xml is not None:
            d["xml"] = self.xml
            d["xml_sha256"] = hashlib.sha256(self.xml.encode("utf-8")).hexdigest()
        return d


def material_names() -> list[str]:
    """The names ``--material`` accepts for the packaged material files."""
    return sorted(p.stem for p in MATERIALS_DIR.glob("*.toml"))


def _albedo(v, name: str, where=None) -> tuple[float, ...]:
    """One grey albedo or three (R, G, B): a number, ``R/G/B`` text or a list of three."""
    parts = v.split("/") if isinstance(v, str) else (list(v) if isinstance(v, (list, tuple)) else [v])
    try:
        vals = tuple(float(x) for x in parts)
    except (TypeError, ValueError):
        raise InputError(f"Ward parameters: {name}={v!r} is not a number or R/G/B numbers", path=where) from None
    if len(vals) not in (1, 3):
        raise InputError(f"Ward parameters: {name} takes one value or three (R/G/B), got {len(vals)}", path=where)
    return vals


def _ward_material(values: dict, label: str, where=None, what: str = "ward material") -> Material:
    """A Ward material from ``rho_d``, ``rho_s`` (grey or R, G, B), ``alpha_x``, ``alpha_y``
    and ``lobe_rotation`` (radians or ``WardParams.parse``'s angle text)."""
    from glossrig.core.samples import LUMINANCE_WEIGHTS

    try:
        rho = {k: _albedo(values[k], k, where) for k in ("rho_d", "rho_s")}
        shape = dict(alpha_x=float(values["alpha_x"]), alpha_y=float(values["alpha_y"]),
                     lobe_rotation=parse_angle(values.get("lobe_rotation", 0.0)))
    except KeyError as e:
        raise InputError(f"{what} lacks {e.args[0]}", path=where) from None
    except (TypeError, ValueError) as e:
        raise InputError(f"{what}: {e}", path=where) from None
    if all(len(v) == 1 for v in rho.values()):
        w = WardParams(rho_d=rho["rho_d"][0], rho_s=rho["rho_s"][0], **shape)
        return Material("ward", label, ward=check_physical(w, where=where, what=what))
    rgb = {k: v * 3 if len(v) == 1 else v for k, v in rho.items()}
    for i, c in enumerate("rgb"):           # every channel a physical Ward BRDF of its own
        check_physical(WardParams(rho_d=rgb["rho_d"][i], rho_s=rgb["rho_s"][i], **shape), where=where,
                       what=f"{what} ({c} channel)")
    lum = {k: float(sum(wt * x for wt, x in zip(LUMINANCE_WEIGHTS, v))) for k, v in rgb.items()}
    return Material("ward", label, ward=WardParams(**lum, **shape), rgb=rgb)


def _from_table(d: dict, label: str, where) -> Material:
    kind = d.get("type")
    if kind == "ward":
        return _ward_material(d, label, where)
    if kind == "lambert":
        return lambert(float(d.get("albedo", -1)), label)
    if kind == "measured":
        return measured(d["path"], label)
    raise InputError(f"material type must be ward, lambert or measured, got {kind!r}", path=where)


def lambert(albedo: float, label: str | None = None) -> Material:
    if not (0 <= albedo <= 1):
        raise InputError(f"Lambertian albedo must lie in [0, 1], got {albedo}")
    return Material("lambert", label or f"lambert:{albedo:g}", albedo=albedo)


def measured(path: str | Path, label: str | None = None) -> Material:
    p = Path(path)
    if not p.is_file():
        raise InputError("measured BSDF file not found", path=p)
    return Material("measured", label or p.stem, path=str(p.resolve()))


def mitsuba_xml(path: str | Path, label: str | None = None) -> Material:
    """A stock Mitsuba 3 BSDF description (XML text; loaded and checked by the twin). A
    path that is not a file is looked up in the packaged ``scenes/materials`` (with or
    without ``.xml``)."""
    p = Path(path)
    packaged = [q for q in (MATERIALS_DIR / p.name, MATERIALS_DIR / f"{p.name}.xml") if q.is_file()]
    if not p.is_file():
        if len(p.parts) != 1 or not packaged:
            raise InputError("Mitsuba BSDF file not found", path=p)
        p = packaged[0]
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"Mitsuba BSDF file cannot be read as UTF-8 text: {e}", path=p) from None
    return Material("mitsuba", label or p.stem, path=str(p.resolve()), xml=text)


def material_sha256(spec: str) -> str | None:
    """The sha256 of the files a material spec is read from, or None where the spec's text is
    the whole material (``ward:``, ``lambert:``): a packaged name's TOML file (and the
    ``.bsdf`` file a ``type = "measured"`` one names), a ``measured:`` file, a ``mitsuba:``
    XML file. A capture records it (:func:`glossrig.twin.simulate.sample_options`), so a
    capture is resumed or reused only with the material it was made of - an edited file at
    the same path is another material. One file: its own sha256 (as ``sha256sum`` prints
    it); several: the sha256 of their sha256s, one per line, in the order above. A Mitsuba
    XML that names further files (a texture, a spectrum) has only the XML itself hashed."""
    from glossrig.core.capture import sha256_file

    spec = spec.strip()
    files: list[Path] = []
    if not spec.startswith(("ward:", "lambert:", "measured:", "mitsuba:")):
        files.append(MATERIALS_DIR / f"{spec}.toml")
    m = parse_material(spec)
    if m.path is not None:
        files.append(Path(m.path))
    if not files:
        return None
    sums = [sha256_file(f) for f in files]
    return sums[0] if len(sums) == 1 else hashlib.sha256("\n".join(sums).encode()).hexdigest()


def parse_material(spec: str) -> Material:
    """Parse a material spec (see module docstring); errors name the spec."""
    spec = spec.strip()
    if spec.startswith("ward:"):
        text = spec[5:]
        if "/" not in text:
            return Material("ward", spec, ward=WardParams.parse(text))
        values: dict = {}
        for part in text.split(","):
            if part.strip():
                if "=" not in part:
                    raise InputError(f"Ward parameters: expected name=value, got {part!r} in {text!r}")
                k, v = part.split("=", 1)
                values[k.strip()] = v.strip()
        unknown = set(values) - {"rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation"}
        if unknown:
            raise InputError(f"Ward parameters: unknown parameter {sorted(unknown)[0]!r} in {text!r}")
        return _ward_material(values, spec, what=f"Ward parameters {text!r}")
    if spec.startswith("lambert:"):
        try:
            a = float(spec[8:])
        except ValueError:
            raise InputError(f"lambert:ALBEDO expects a number, got {spec!r}") from None
        return lambert(a, spec)
    if spec.startswith("measured:"):
        return measured(spec[9:])
    if spec.startswith("mitsuba:"):
        return mitsuba_xml(spec[8:])
    f = MATERIALS_DIR / f"{spec}.toml"
    if not f.is_file():
        raise InputError(f"unknown material {spec!r}: not ward:/lambert:/measured:/mitsuba: and not one of "
                         f"{', '.join(material_names())}")
    return _from_table(read_toml(f, "material file"), spec, f)
