"""Material descriptions: what a sample is made of, as data.

A material spec (``glossrig simulate --material``) is one of
``ward:rho_d=..,rho_s=..,alpha_x=..,alpha_y=..,lobe_rotation=..`` (lobe_rotation in
radians, or with a unit: ``140deg``, ``2.44rad``; every value is range-checked by
:func:`glossrig.core.models.ward.check_physical`: rho_d in [0, 1], rho_s >= 0,
rho_d + rho_s <= 1, 0 < alpha <= 0.5 as in thesis Table 4.2, |lobe_rotation| <= 2 pi),
``lambert:ALBEDO``, ``measured:PATH`` (an RGL ``.bsdf`` file, Dupuy & Jakob 2018)
or the name of a file in ``scenes/materials`` (the packaged scenes,
:func:`glossrig.core.resources.scenes_dir`, so the names work wherever glossrig is
installed and from any folder).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from glossrig.core.errors import InputError
from glossrig.core.resources import scenes_dir
from glossrig.core.models.ward import WardParams, check_physical, parse_angle
from glossrig.core.toml_input import read_toml

#: the packaged material descriptions (one TOML file per name)
MATERIALS_DIR = scenes_dir() / "materials"


@dataclass(frozen=True)
class Material:
    kind: str                     # "ward" | "lambert" | "measured"
    label: str
    ward: WardParams | None = None
    albedo: float | None = None
    path: str | None = None

    def to_json(self) -> dict:
        d = {"kind": self.kind, "label": self.label}
        if self.ward is not None:
            d["ward"] = self.ward.as_dict()
        if self.albedo is not None:
            d["albedo"] = self.albedo
        if self.path is not None:
            d["path"] = self.path
        return d


def material_names() -> list[str]:
    """The names ``--material`` accepts for the packaged material files."""
    return sorted(p.stem for p in MATERIALS_DIR.glob("*.toml"))


def _from_table(d: dict, label: str, where) -> Material:
    kind = d.get("type")
    if kind == "ward":
        try:
            w = WardParams(**{k: float(d[k]) for k in ("rho_d", "rho_s", "alpha_x", "alpha_y")},
                           lobe_rotation=parse_angle(d.get("lobe_rotation", 0.0)))
        except KeyError as e:
            raise InputError(f"ward material lacks {e.args[0]}", path=where) from None
        except (TypeError, ValueError) as e:
            raise InputError(f"ward material: {e}", path=where) from None
        return Material("ward", label, ward=check_physical(w, where=where, what="ward material"))
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


def parse_material(spec: str) -> Material:
    """Parse a material spec (see module docstring); errors name the spec."""
    spec = spec.strip()
    if spec.startswith("ward:"):
        return Material("ward", spec, ward=WardParams.parse(spec[5:]))
    if spec.startswith("lambert:"):
        try:
            a = float(spec[8:])
        except ValueError:
            raise InputError(f"lambert:ALBEDO expects a number, got {spec!r}") from None
        return lambert(a, spec)
    if spec.startswith("measured:"):
        return measured(spec[9:])
    f = MATERIALS_DIR / f"{spec}.toml"
    if not f.is_file():
        raise InputError(f"unknown material {spec!r}: not ward:/lambert:/measured: and not one of "
                         f"{', '.join(material_names())}")
    return _from_table(read_toml(f, "material file"), spec, f)
