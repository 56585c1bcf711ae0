"""Meshes in and out: the `Mesh` type, reading and checking mesh files, intake (welding,
outward winding), a file's polygon layout and part labels, mesh hand-off files, the
simplified proxies of dense meshes and the store that keeps them on disk during a run."""
