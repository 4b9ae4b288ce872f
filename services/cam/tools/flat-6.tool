# 6 mm flat end mill, carbide, 3 flutes: the default roughing tool.
name = flat-6
type = flat
diameter_mm = 6
cutting_length_mm = 18
shank_diameter_mm = 6
stickout_mm = 35
holder_diameter_mm = 32
holder_length_mm = 40
flutes = 3
