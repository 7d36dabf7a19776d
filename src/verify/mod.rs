//! Verification: in = program text (+ robot and cell); out = what the program really commands,
//! re-read from the text. [`gcode`] is the reader `verify` and `simulate` share.

pub mod gcode;
