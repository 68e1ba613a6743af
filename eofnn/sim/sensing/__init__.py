"""Sensing: what the wavefront sensor sees of the turbulence. Today's kernels (the mean over each actuator's
subaperture, or point samples) are transfer functions the Fourier synthesis applies to the spectrum."""
