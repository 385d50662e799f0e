"""The worker pipeline: visual hull -> surface -> per-frame skeletons -> spine (Brostow et al. 2004)."""
