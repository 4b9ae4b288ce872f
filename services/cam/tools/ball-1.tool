# 1 mm ball end mill, carbide, 2 flutes: fine finishing.
name = ball-1
type = ball
diameter_mm = 1
cutting_length_mm = 3
shank_diameter_mm = 3
stickout_mm = 15
holder_diameter_mm = 32
holder_length_mm = 40
flutes = 2
