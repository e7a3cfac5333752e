"""Stereo: rectification, dense matching, exact reconstruction, the water-level refinement, surveys."""
