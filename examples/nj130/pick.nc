(pick and place: a user's joint-move program for the NJ-130 of docs/tutorial.md)
G21 G90 G94
G0 X60 Y0 Z-40 A80 B-80 C-20 (approach)
M0 (mount the gripper)
G93
G64 P5
G1 X60 Y0 Z-40 A80 B-40 C-20 F200 (pick)
G1 Z-60 A140 B-80 C-100 F180
G61
G1 X80 Y-20 Z-40 A160 B20 C-160 F100 (place)
G4 P0.5
G1 X100 Y20 Z0 A140 B80 C-140 F120 (retract)
G94
M0 (remove the gripper)
M2
