"""glossrig.core.report.document: The measurement report: HTML/Markdown document, its figures, ground-truth recovery of twin measurements."""
