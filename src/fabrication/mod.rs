//! The fabrication stage: height map -> phase wrapping -> quantization -> grayscale
//! lithography masks, multi-level binary GDSII mask set, STL.

pub mod stl;
