"""glossrig.core.extraction: From a capture to BRDF samples (thesis 4.3.5-4.4): per-pixel cylinder geometry, the extraction stage, its diagnostic plots."""
