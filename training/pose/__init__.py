"""Full-body pose from sparse IMUs (Zheng et al. 2021; Vlutters 2016)."""
