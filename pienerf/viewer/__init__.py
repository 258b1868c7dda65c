"""Front ends of the interactive demo: the shared loop pieces, the viser viewer and the meshcat viewer."""
