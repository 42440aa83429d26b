"""WorldTree: hierarchical dynamic Gaussian reconstruction from monocular video (library, no CLI code)."""

__version__ = "0.1.0"
