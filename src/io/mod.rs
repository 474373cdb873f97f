//! Files: ENVI spectral cubes, OpenEXR parameter maps, angle maps.

pub mod angle_map;
