"""Fusion backends behind one interface (:class:`mapping.fusion.base.FusionBackend`)."""
