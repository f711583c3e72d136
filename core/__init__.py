"""glossrig.core: the measurement pipeline and models.

Raw files -> calibrated geometry -> HDR -> BRDF samples -> fits -> reproduction
model -> fabrication toolpaths. Knows nothing of Mitsuba or of any device
(design.md): the twin and the hardware layer use its data types, never the
other way round (enforced by tests/test_layering.py).

The subpackages follow that data flow; the files every stage shares sit at the top.

========================  ===================================================
Top level                 What it holds
========================  ===================================================
``rig``                   the rig file (design.md), typed and validated once
``capture``               the capture folder contract: capture.json, raw names
``samples``               the BRDF samples table contract
``errors``                errors a user sees (file-named, exit code 2)
``toml_input``            the one TOML/JSON reader with file-named errors
``resources``             where packaged scenes are; how a path option resolves
``atomic``                the one atomic file write (temporary file, fsync, rename)
``checkpoint``            fingerprints, resume
``provenance``            what an output was made from and by which code
``progress``              when progress bars show
========================  ===================================================

Thesis section -> module (S. Cucerca, "Reflectance measurement and fabrication tools for gloss
editing", MSc thesis, Saarland University 2019; equations as cited in each module's docstring):

=========================================  ==========================================
Thesis                                     Module
=========================================  ==========================================
2.1, 4.5.1 extended Ward (eq. 2.5)         ``models.ward`` (the one evaluation + Jacobian)
4.3.5 geometric values (angles)            ``models.angles``, ``extraction.cylinder``
4.1.4 sample part, markers (eq. 4.18-24)   ``calibration.markers``
4.3.1 image preprocessing (raw)            ``calibration.raw``, ``calibration.demosaic``
4.3.2 geometric calibration: intrinsics    ``calibration.intrinsics``
4.3.2 markers, holder/cylinder poses       ``calibration.marker_detect``, ``calibration.poses``
4.3.3 radiometric calibration (HDR)        ``radiometry.hdr`` (eq. 4.31-4.44)
4.3.3 patch normalisation                  ``radiometry.patch`` (eq. 4.45-4.50)
4.2.2 exposure sequence (planning)         ``radiometry.exposure_plan``
4.3.4 lamp position                        ``calibration.lamps`` (eq. 4.51-4.53)
4.3-4.4 samples, diffuse normalisation     ``extraction.extract``
4.5.2 optimisation (fit)                   ``fitting.fit``, ``fitting.fit_plots``
(exports, fit.json reader)                 ``fitting.export``, ``fitting.material_export``
6.1-6.2 reproduction model, ETN            ``reproduction.model`` (fabrication reads its ETN)
5.1-5.2 fabrication (halftone -> cuts)     ``fabrication`` (``halftone``, ``vectorize``, ``toolpath``, ...)
7.1.3 BRDF space coverage                  ``design.coverage``, ``design.placement``, ``design.fisher``
7.2.1 model validation                     ``reproduction.model`` (leave-one-out)
(beyond the thesis) gloss units            ``models.gloss``; pixel footprint ``models.footprint``
(beyond the thesis) diagnose               ``diagnose`` (residual causes, catalogue)
(beyond the thesis) report                 ``report.document``, ``report.figures``, ``report.recovery``
=========================================  ==========================================
"""
