MODULE user
  ! compensate test program: a user's joint moves for the NJ-130
  CONST jointtarget jStart := [[60, 0, -40, 80, -80, -20], [9E+09, 9E+09, 9E+09, 9E+09, 9E+09, 9E+09]];
  PROC main()
    MoveAbsJ jStart\NoEOffs, v1000, fine, tool0;
    Stop;
    MoveAbsJ [[60, 0, -40, 80, -40, -20], [9E+09, 9E+09, 9E+09, 9E+09, 9E+09, 9E+09]]\NoEOffs, v1000\T:=0.3, z5, tool0;
    MoveAbsJ [[60, 0, -60, 140, -80, -100], [9E+09, 9E+09, 9E+09, 9E+09, 9E+09, 9E+09]]\NoEOffs, v1000\T:=0.334, fine, tool0;
    WaitTime 0.5;
    MoveAbsJ [[80, -20, -40, 160, 20, -160], [9E+09, 9E+09, 9E+09, 9E+09, 9E+09, 9E+09]]\NoEOffs, v1000\T:=0.6, fine, tool0;
    MoveAbsJ jStart\NoEOffs, v1000\T:=1.0, fine, tool0;
    Stop;
  ENDPROC
ENDMODULE
