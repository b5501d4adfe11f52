"""Sphinx configuration of the scopetwin documentation: ``make docs`` writes HTML into ``build/docs``."""

from __future__ import annotations

from scopetwin import __version__

project = "scopetwin"
author = "the scopetwin authors"
copyright = "the scopetwin authors"
version = release = __version__

extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]

# MyST: headings get anchors (contract.md's sections are linked by name), ``{include}`` pulls in ARCHITECTURE.md
myst_heading_anchors = 3
myst_enable_extensions = ["colon_fence"]

# the docstrings are numpydoc style
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"

html_theme = "furo"
html_title = f"scopetwin {version}"
