"""Rendering: the landmark renderer, its CPU ray-cast reference, the sun and camera
effects. Imports terrain and camera."""
