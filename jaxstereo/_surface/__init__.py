"""Surfaces: DEMs from surveys, profiles, and the damage of an armour layer."""
