# 6 mm bull-nose end mill with 1 mm corner radius, 3 flutes.
name = bull-6-1
type = bull
diameter_mm = 6
corner_radius_mm = 1
cutting_length_mm = 18
shank_diameter_mm = 6
stickout_mm = 35
holder_diameter_mm = 32
holder_length_mm = 40
flutes = 3
