"""glossrig.core.design.placement: Rig design (thesis 7.1.3): BRDF-space coverage, LED placement, expected parameter errors."""
