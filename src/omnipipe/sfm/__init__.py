"""Camera-motion stage (paper Sec. V): stationary frames, two-view geometry on rays
(eight-point, RANSAC), and metric scale from the laser (Eq. 17)."""
