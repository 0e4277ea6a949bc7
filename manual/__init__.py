"""The manual's build helpers (mkdocs.yml names :mod:`manual.hooks`); not installed."""
