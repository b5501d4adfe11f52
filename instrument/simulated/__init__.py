"""Simulated devices acting on a shared virtual world, and the renderers their cameras use."""
