"""Geometry: poses, cameras, the water interface, exact and first-order refraction, triangulation."""
