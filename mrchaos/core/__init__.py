"""The foundations every layer uses: errors, atomic writes, planar geometry, the rasteriser (metres to pixels)."""
