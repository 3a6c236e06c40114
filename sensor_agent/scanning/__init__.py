"""Scanner backends behind one small interface (``base.ScannerBackend``): bleak, replay, simulated."""
