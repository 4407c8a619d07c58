"""Points and meshes from matches."""
