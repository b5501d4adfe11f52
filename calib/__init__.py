"""calib: from camera images to setup parameters — one-shot camera and setup calibration (no Mitsuba)."""
