; hand-written Marlin job without slicer hints
G21 ; millimetres
G90
M83
G28
M104 S225
M109 S225

N1 G92 E0*70
N2 G0 Z0.2 F600*45
G0 X20 Y20 F6000
g1 x40 y20 e1.25903 f900 ; lower case
(quarter arc, counter-clockwise about X40 Y30)
G3 X50 Y30 I0 J10 E0.98884
G10 ; firmware retraction
G0 Z0.7
G0 X20 Y50
G0 Z0.2
G11

G91 ; relative positions (Marlin 2: E too)
G1 X10 E0.46321
G1 Y10 E0.46321
G90 (back to absolute: Marlin 2 resets E to absolute)
M83
G10
G0 Z0.7
G20 ; inches
G0 X2.755906 Y1.574803
G0 Z0.007874
G11
G2 I-0.196850 J0 E0.098430 ; full circle, clockwise
G21
G10
G0 Z10
M104 S0
M84
