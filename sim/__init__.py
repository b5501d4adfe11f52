"""sim: synthetic truth — surfaces, measurement simulation, datasets, studies and the command line."""
