"""glossrig.hardware: device protocols (lights, camera, engraver), their real
and virtual implementations, and the capture orchestrator."""
