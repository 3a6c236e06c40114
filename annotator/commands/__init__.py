"""One module per `annotator` command; each exposes `register(app)` and stays thin."""
