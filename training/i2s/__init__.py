"""IMU-to-segment assignment and alignment (Zimmermann et al. 2018)."""
