; two straight beads, 0.4 mm high, on the fabric
G21
G90
M83
;HEIGHT:0.4
;WIDTH:1.5
G1 Z0.4 F1200
G0 X10 Y10
G1 X40 Y10 E2.0
G0 X10 Y20
G1 X40 Y20 E2.0
