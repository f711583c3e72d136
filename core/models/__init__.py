"""glossrig.core.models: Models of reflectance: the one extended Ward BRDF with its Jacobian, BRDF angles, a sample's footprint, gloss units, material descriptions."""
