"""Stock Mitsuba 3 BSDFs as the twin's sample (``--material mitsuba:FILE.xml``).

Any BSDF Mitsuba 3 ships can be put on the sample, so that materials no one here wrote
can be measured - in particular anisotropic ones (``roughconductor`` with ``alpha_u !=
alpha_v``, GGX or Beckmann, with its conductor Fresnel term; ``principled`` with
``anisotropic``). Mitsuba 3.9's ``roughplastic`` is isotropic only (it refuses
``alpha_u``/``alpha_v``). The file holds one ``<bsdf type="...">`` element; a missing
``version`` attribute is taken as ``3.0.0``. It is loaded with ``mi.load_string`` from
the text core read (:attr:`glossrig.core.models.materials.Material.xml`, so what is
rendered is what truth.json records), file names inside it resolving against the file's
folder. Errors name the file (:class:`glossrig.core.errors.InputError`, exit 2).

Sample rotation: the stock BSDF is wrapped in ``glossrig_rotated``
(:mod:`glossrig.twin.rotated_bsdf`), which turns its tangent frame about the normal by
the sample rotation, as ``glossrig_ward`` does. On the twin's cylinder Mitsuba's ``s``
axis runs around the cylinder (``axis x normal``, thesis eq. 4.61), so at rotation 0 the
material's ``u`` axis (``alpha_u``) runs around the cylinder and ``v`` (``alpha_v``) along
its axis; a rotation of 90 degrees swaps them.

Ground truth: :class:`MitsubaBRDF` evaluates the loaded BSDF with ``mi.BSDFContext`` at
any direction pair, through the same wrapper the render uses, with the conventions of
:class:`glossrig.twin.measured_brdf.MeasuredBRDF` (``wi`` to the light, ``wo`` to the
camera, BRDF f in 1/sr per RGB channel). Directions are in a frame (x = tangent, y =
``n x t``, z = normal) in which the material's ``u`` axis is the tangent turned by
``rotation_deg``: 0 for the angles of a samples table (they are measured in the sample's
own, rotated frame), the sample rotation for directions in the rig's unrotated frame.
:meth:`MitsubaBRDF.from_json` rebuilds it from truth.json's ``material``.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.models.materials import Material

from .measured_brdf import MeasuredBRDF

#: the version a description without one is read as (Mitsuba 3's XML format)
DEFAULT_VERSION = "3.0.0"


def _checked_text(text: str, where) -> str:
    """The description's text with a ``version`` on its root; the root must be one ``<bsdf>``."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise InputError(f"not a well-formed XML BSDF description: {e}", path=where) from None
    if root.tag != "bsdf":
        raise InputError(f"the root element must be <bsdf type=\"...\">, got <{root.tag}>", path=where)
    if "type" not in root.attrib:
        raise InputError("the <bsdf> element has no type attribute (e.g. type=\"roughconductor\")", path=where)
    if "version" in root.attrib:
        return text
    root.set("version", DEFAULT_VERSION)
    return ET.tostring(root, encoding="unicode")


def load_bsdf(material: Material):
    """The stock BSDF of a ``mitsuba`` material, loaded by Mitsuba (``mi.load_string``)."""
    from .mitsuba_env import mitsuba

    if material.kind != "mitsuba" or material.xml is None:
        raise InputError(f"material {material.label!r} is not a Mitsuba BSDF description")
    where = material.path or material.label
    text = _checked_text(material.xml, where)
    mi = mitsuba()
    resolver = mi.file_resolver()
    folder = str(Path(where).resolve().parent) if material.path else None
    if folder:
        resolver.prepend(folder)
    try:
        bsdf = mi.load_string(text)
    except Exception as e:       # Mitsuba reports every load error as RuntimeError (or subclasses)
        msg = str(e).strip()
        if msg.startswith("[") and "] " in msg:
            msg = msg.split("] ", 1)[1]     # drop Mitsuba's "[parser.cpp:1718]"
        raise InputError(f"Mitsuba cannot load this BSDF: {msg}", path=where) from None
    finally:
        if folder:
            _drop_first(resolver, folder)
    if not isinstance(bsdf, mi.BSDF):
        raise InputError(f"does not describe a BSDF (Mitsuba made a {type(bsdf).__name__})", path=where)
    return bsdf


def _drop_first(resolver, folder: str) -> None:
    """Undo ``resolver.prepend(folder)`` (the resolver has no remove: rebuild it)."""
    paths = [str(resolver[i]) for i in range(len(resolver))]
    if paths and paths[0] == folder:
        resolver.clear()
        for p in paths[1:]:
            resolver.append(p)


def rotated_dict(material: Material, tangent_rotation_rad: float = 0.0) -> dict:
    """Scene dict of the sample: the stock BSDF inside ``glossrig_rotated``."""
    return {"type": "glossrig_rotated", "bsdf": load_bsdf(material), "tangent_rotation": float(tangent_rotation_rad)}


class MitsubaBRDF(MeasuredBRDF):
    """A ``mitsuba`` material's true BRDF at any directions (module docstring)."""

    def __init__(self, material: Material):
        from .mitsuba_env import mitsuba

        self.mi = mitsuba()
        self.material = material
        self.path = Path(material.path) if material.path else None
        self.bsdf = self.mi.load_dict(rotated_dict(material))
        self._params = self.mi.traverse(self.bsdf)

    @classmethod
    def from_json(cls, d: dict) -> MitsubaBRDF:
        """From truth.json's ``material`` (its recorded XML text, not the file, which may have changed)."""
        if d.get("kind") != "mitsuba" or "xml" not in d:
            raise InputError(f"not a Mitsuba material record: kind {d.get('kind')!r}")
        return cls(Material("mitsuba", d.get("label", "mitsuba"), path=d.get("path"), xml=d["xml"]))

    def eval(self, wi, wo, rotation_deg: float = 0.0) -> np.ndarray:
        """RGB BRDF (..., 3) for light ``wi`` and camera ``wo`` in a frame whose tangent the
        material's ``u`` axis makes ``rotation_deg`` with (module docstring)."""
        self._params["tangent_rotation"] = math.radians(rotation_deg)
        self._params.update()
        return super().eval(wi, wo)

    def table(self, t, rotation_offset_deg: float = 0.0) -> np.ndarray:
        """RGB BRDF at the angles of a samples table's rows; ``rotation_offset_deg``: the
        twin's ``sample_rotation_offset`` (the sample sat that much further turned than the
        nominal rotation the table's angles are measured at)."""
        from glossrig.core.models.angles import local_direction

        a = {c: np.asarray(t[c], float) for c in ("theta_in", "phi_in", "theta_out", "phi_out")}
        return self.eval(local_direction(a["theta_in"], a["phi_in"]), local_direction(a["theta_out"], a["phi_out"]),
                         rotation_offset_deg)
