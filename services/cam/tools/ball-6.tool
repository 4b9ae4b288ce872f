# 6 mm ball end mill, carbide, 2 flutes.
name = ball-6
type = ball
diameter_mm = 6
cutting_length_mm = 18
shank_diameter_mm = 6
stickout_mm = 35
holder_diameter_mm = 32
holder_length_mm = 40
flutes = 2
