"""New meshes from landmarks: embedded deformation of a template, the quality gate of
generated meshes, and gated sampling (next template, stiffer, redraw)."""
