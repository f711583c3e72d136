"""glossrig.core.reproduction.model: The gloss reproduction model (thesis chapter 6): bases, the ETN and its validation."""
