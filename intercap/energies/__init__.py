"""What the fits minimise: loss terms, one small function per equation (losses.py), the
body priors (priors.py), the learned motion priors (motion_prior.py) and the shared
L-BFGS loop (optim.py). Imports torch, geometry and body_models; no stage."""
