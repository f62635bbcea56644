"""Figures and videos: body renders, overlays, flow colour coding, joint traces."""
