# 3 mm ball end mill, carbide, 2 flutes: the default finishing tool.
name = ball-3
type = ball
diameter_mm = 3
cutting_length_mm = 9
shank_diameter_mm = 3
stickout_mm = 25
holder_diameter_mm = 32
holder_length_mm = 40
flutes = 2
