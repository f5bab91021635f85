"""Core types and units, imported by every other layer: poses, cameras, maps, priors, images, costs, atomic file
output, and the Taichi backend's start-up."""
