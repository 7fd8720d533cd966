"""Sphinx configuration of the API reference: autodoc reads the docstrings, napoleon their numpydoc sections.

Built by ``.ci/run`` with warnings as errors:
``python -m sphinx -W --keep-going -b html docs/api build/api``.
"""

from importlib.metadata import version as _version

project = "quadobs"
release = _version("quadobs")
extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.mathjax"]
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_ivar = True  # Attributes as fields: a property documented twice is not a duplicate
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": True}
# Names the docstrings mention by their short form, resolved by readers, not by links.
nitpicky = False
html_theme = "alabaster"
exclude_patterns = ["_build"]
