"""Figures and their formats: piece sets, figures, interchange JSON and KILOGRAM SVG, the built-in library,
families, contact sheets."""
