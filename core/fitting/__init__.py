"""glossrig.core.fitting: Fitting the extended Ward model to samples (thesis 4.5, 6.2), its plots, the fit.json reader/writer and exports."""
