"""recon: from camera images to surfaces — markers, gradients, heights, focus maps (no Mitsuba)."""
