"""pregrasp's application layer: the command line (``app.cli``) and the viser inspection app."""
