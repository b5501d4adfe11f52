"""The Mitsuba 3 realisation of the world model.

This is the only package of scopetwin that imports Mitsuba, and it does so
lazily: ``import scenes`` never loads it, and importing a module of this package
sets no variant. Every builder and renderer here takes its ``variant`` explicitly
(default :func:`scopetwin.scenes.mitsuba.variant.choose` of its kind, resolved when it is
called) and sets it for the call (:func:`scopetwin.scenes.mitsuba.variant.mitsuba`).
"""
