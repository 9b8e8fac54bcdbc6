"""Rendering rules shared by every backend (CPU kernels, reference compositing, projection).

Compositing (the 3DGS rules, made tile-independent): a Gaussian touches a pixel iff its
Mahalanobis distance² <= MAHA_CUTOFF (the 3σ ellipse) and alpha = min(ALPHA_MAX, o·exp(-d²/2))
>= ALPHA_MIN; a pixel stops before the Gaussian that would push its transmittance below T_MIN.
Projection: EPS2D is the low-pass dilation added to the 2D covariance diagonal (pixels²);
Gaussians closer than NEAR to the camera plane are culled.
"""

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
MAHA_CUTOFF = 9.0

EPS2D = 0.3
NEAR = 0.01
