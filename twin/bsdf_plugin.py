"""What glossrig's Python BSDF plugins for Mitsuba 3 share: the registration under the
plugin's name (once per process, after :func:`glossrig.twin.mitsuba_env.mitsuba` has set
the variant), and the traversal that exposes their parameters to ``mi.traverse``.

A plugin subclasses :class:`PluginBSDF`, names itself in ``PLUGIN`` (the ``type`` of a
scene dictionary) and lists in ``TRAVERSED`` the attributes a scene may change, each
with whether it is differentiable. The plugins keep no state derived from their
parameters (every evaluation reads them), so a change needs no update step. Mitsuba's
plugin interface: "Mitsuba 3: Developing plugins in Python" (docs, ``mi.register_bsdf``,
``traverse`` and ``parameters_changed``).
"""
from __future__ import annotations

import mitsuba as mi

_registered: set[str] = set()


class PluginBSDF(mi.BSDF):
    #: the plugin's name in a scene description (``{"type": PLUGIN, ...}``)
    PLUGIN = ""
    #: (attribute, differentiable) of each parameter ``mi.traverse`` exposes
    TRAVERSED: tuple[tuple[str, bool], ...] = ()

    def traverse(self, callback):
        for name, differentiable in self.TRAVERSED:
            flags = mi.ParamFlags.Differentiable if differentiable else mi.ParamFlags.NonDifferentiable
            callback.put(name, getattr(self, name), flags)

    def parameters_changed(self, keys):
        pass                 # nothing is derived from the parameters: each evaluation reads them

    @classmethod
    def register(cls) -> None:
        """Make the plugin known to Mitsuba as ``PLUGIN`` (a second call does nothing)."""
        if not cls.PLUGIN:
            raise TypeError(f"{cls.__name__} names no PLUGIN")
        if cls.PLUGIN not in _registered:
            mi.register_bsdf(cls.PLUGIN, lambda props: cls(props))
            _registered.add(cls.PLUGIN)
