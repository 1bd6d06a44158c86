"""Robot colours, shared by the figures and the Foxglove scene (robot i: COLORS[i % len])."""

COLORS = ("#fc7d00", "#2b9e78", "#e02b8f", "#1f77b4", "#9467bd", "#8c564b", "#7f7f7f")
