"""glossrig.core.radiometry: Radiometry (thesis 4.3.3): HDR from exposure sequences, patch (light) normalisation, exposure planning."""
