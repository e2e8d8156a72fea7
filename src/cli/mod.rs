//! The command line's parts: its grammar ([`args`]), what the commands share ([`options`]) and,
//! one module per stage, each command's arguments, its run (options to the library, result to
//! the printer) and its printing.

pub mod args;
pub mod calibration;
pub mod decoder;
pub mod demo;
pub mod fabrication;
pub mod metrology;
pub mod optics;
pub mod options;
