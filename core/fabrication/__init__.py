"""Gloss fabrication: a target coverage image -> an engraver toolpath (thesis ch. 5, 7.2).

Pipeline (thesis 5.2): coverage image (:mod:`.inputs`; a material map goes through the
reproduction model's ETN first, :func:`glossrig.core.reproduction.model.load_etn`, thesis
6.1 and 7.2.2) -> juxtaposed
halftone (:mod:`.halftone`, Babaei & Hersch 2013) -> scratch segments along the
discrete lines (:mod:`.vectorize`) -> rotation onto the machine's y axis, shift and
scale (:mod:`.layout`, eq. 5.2-5.3) -> ordered cuts with bed and depth checks
(:mod:`.toolpath`) -> G-code or Roland RML-1 (:mod:`.gcode`, :mod:`.rml`) and
previews (:mod:`.preview`; the predicted print lit and rendered beside the target,
:mod:`.appearance`, thesis fig. 7.7). :mod:`.pipeline` runs it end to end; :mod:`.rasterize`
maps a machine file back onto the halftone grid to check it.
"""
from glossrig.core.fabrication.machine import Machine, ScreenParams, load_machine
from glossrig.core.fabrication.pipeline import Plan, fabricate, plan, write

__all__ = ["Machine", "ScreenParams", "load_machine", "Plan", "fabricate", "plan", "write"]
