"""Virtual dome: LED geometry, cameras, polarised rendering, sensor realism, dataset format."""
