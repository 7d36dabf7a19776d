/PROG  USER
/ATTR
OWNER = MNEDITOR;
COMMENT = "user";
LINE_COUNT = 9;
DEFAULT_GROUP = 1,*,*,*,*;
/MN
   1:  !compensate test program ;
   2:  J P[1] 100% FINE ;
   3:  PAUSE ;
   4:  J P[2] 50% CNT5 ;
   5:  J P[3] 50% FINE ;
   6:  WAIT 0.50(sec) ;
   7:  J P[4] 1.50sec FINE ;
   8:  J P[1] 100% FINE ;
   9:  PAUSE ;
/POS
P[1]{
   GP1:
    UF : 0, UT : 1,
    J1=    60.000 deg,    J2=     0.000 deg,    J3=   -40.000 deg,
    J4=    80.000 deg,    J5=   -80.000 deg,    J6=   -20.000 deg
};
P[2]{
   GP1:
    UF : 0, UT : 1,
    J1=    60.000 deg,    J2=     0.000 deg,    J3=   -40.000 deg,
    J4=    80.000 deg,    J5=   -40.000 deg,    J6=   -20.000 deg
};
P[3]{
   GP1:
    UF : 0, UT : 1,
    J1=    60.000 deg,    J2=     0.000 deg,    J3=   -60.000 deg,
    J4=   140.000 deg,    J5=   -80.000 deg,    J6=  -100.000 deg
};
P[4]{
   GP1:
    UF : 0, UT : 1,
    J1=    80.000 deg,    J2=   -20.000 deg,    J3=   -20.000 deg,
    J4=   160.000 deg,    J5=    20.000 deg,    J6=  -160.000 deg
};
/END
