(compensate test program: a user's joint moves for the NJ-130)
G21 G90 G94
G0 X60 Y0 Z-40 A80 B-80 C-20 (approach)
M0 (mount the tool)
G93
G64 P5
G1 X60 Y0 Z-40 A80 B-40 C-20 F200
G1 Z-60 A140 B-80 C-100 F180 (X and Y are modal)
G61
G1 X80 Y-20 Z-40 A160 B20 C-160 F100
G4 P0.5
N100 G1 X 100 Y20 Z0 A140 B80 C-140 F120 ; a block number and a spaced word
G94
M0 (remove the tool)
M2
