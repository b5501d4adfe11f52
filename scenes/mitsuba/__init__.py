"""The Mitsuba 3 realisation of the world model.

This is the only package of scopetwin that imports Mitsuba, and it does so
lazily: ``import scenes`` never loads it. Call :func:`scenes.mitsuba.variant.use`
(or any builder here, which calls it) before touching ``mitsuba``.
"""
