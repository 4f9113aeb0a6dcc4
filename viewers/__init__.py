"""Interactive PyVista apps for o3drbf (``o3drbf view``); never imported by ``o3drbf`` itself."""
