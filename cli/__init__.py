"""glossrig.cli: the thin command-line layer over core, twin and hardware."""
