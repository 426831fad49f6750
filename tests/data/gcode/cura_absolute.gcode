;FLAVOR:Marlin
;TIME:95
;Filament used: 0.0052m
;Layer height: 0.2
;MINX:49.6
;MINY:49.5
;MINZ:0.3
;MAXX:80.5
;MAXY:62.5
;MAXZ:0.5
;TARGET_MACHINE.NAME:Ultimaker 2
;Generated with Cura_SteamEngine 5.6.0
M140 S0
M105
M190 S0
M104 S225
M105
M109 S225
M82 ;absolute extrusion mode
G28 ;Home
G1 Z15.0 F6000 ;Move the platform down 15mm
;Prime the extruder
G92 E0
G1 F200 E3
G92 E0
G92 E0
G1 F2700 E-6.5
;LAYER_COUNT:2
;LAYER:0
M107
G0 F3600 X50 Y50 Z0.3
;TYPE:WALL-OUTER
G1 F2700 E0
G1 F1200 X65 Y50 E0.5189
G1 X80 Y50 E1.03781
G1 F2700 E-5.46219
G1 F300 Z0.8
G0 F3600 X50 Y60
G1 F300 Z0.3
G1 F2700 E1.03781
;TYPE:SKIN
G1 F1200 X80 Y60 E2.35777
G1 X80 Y62 E2.44577
G1 X50 Y62 E3.76573
;MESH:NONMESH
G1 F2700 E-2.73427
;TIME_ELAPSED:60.0
;LAYER:1
G92 E0
M106 S255
G1 F300 Z1
G0 F3600 X50 Y50
G0 Z0.5
;TYPE:WALL-OUTER
G1 F2700 E6.5
G1 F1200 X65 Y50 E6.85603
G1 X80 Y50 E7.21205
G1 F2700 E0.71205
;TIME_ELAPSED:95.0
G91 ;Relative positioning
G1 E-2 F2700 ;Retract a bit
G1 E-2 Z0.2 F2400 ;Retract and raise Z
G1 X5 Y5 F3000 ;Wipe out
G1 Z10 ;Raise Z more
G90 ;Absolute positioning

G1 X0 Y220 ;Present print
M106 S0 ;Turn-off fan
M104 S0 ;Turn-off hotend
M140 S0 ;Turn-off bed

M84 X Y E ;Disable all steppers but Z

M82 ;absolute extrusion mode
M104 S0
;End of Gcode
;SETTING_3 {"global_quality": "[general]\\nversion = 4\\nname = Fine #2\\ndefinition = ultimak
;SETTING_3 er2\\n\\n[metadata]\\ntype = quality_changes\\n\\n[values]\\nadhesion_type = n
;SETTING_3 one\\nlayer_height_0 = 0.3\\n\\n", "extruder_quality": ["[general]\\nversion = 4\\n
;SETTING_3 [values]\\nmaterial_diameter = 2.85\\nmachine_nozzle_size = 0.8\\n\\n"]}
