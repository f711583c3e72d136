"""glossrig.core: the measurement pipeline and models.

Raw files -> calibrated geometry -> HDR -> BRDF samples -> fits -> reproduction
model -> fabrication toolpaths. Knows nothing of Mitsuba or of any device
(design.md): the twin and the hardware layer use its data types, never the
other way round.
"""
