//! Files and the terminal: the OpenVDB/OpenImageIO bridge, grids, images, gradient VDBs, colour
//! maps, charts, tables and progress bars. Uses `volume` only (bricks and transforms as plain data).

pub mod bridge;
pub mod chart;
pub mod colormap;
pub mod exact;
pub mod fingerprint;
pub mod gradient_files;
pub mod images;
pub mod input;
pub mod json;
pub mod make_grid;
pub mod output;
pub mod png_input;
pub mod progress;
pub mod table;
pub mod vdb;
