"""Fine registration against the BIM: surface model, scans, SE(2) registrars, gating, registrar comparison."""
