# 10 mm flat end mill, carbide, 4 flutes: heavy roughing.
name = flat-10
type = flat
diameter_mm = 10
cutting_length_mm = 25
shank_diameter_mm = 10
stickout_mm = 45
holder_diameter_mm = 40
holder_length_mm = 50
flutes = 4
