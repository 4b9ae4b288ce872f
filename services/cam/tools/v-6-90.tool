# 6 mm 90-degree V engraving cutter, 0.2 mm flat tip.
name = v-6-90
type = v
diameter_mm = 6
angle_deg = 90
tip_diameter_mm = 0.2
cutting_length_mm = 10
shank_diameter_mm = 6
stickout_mm = 25
holder_diameter_mm = 32
holder_length_mm = 40
flutes = 2
