"""Research scripts: the studies behind the design notes in docs/notes; not part of the product."""
