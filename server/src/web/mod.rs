//! The database as the web's own clients read it: XYZ Web Mercator height tiles
//! (Terrarium and Mapbox Terrain-RGB) and texture tiles for MapLibre, quantized-mesh
//! tiles on the geographic tiling scheme for CesiumJS, and their PMTiles export.

pub mod build;
pub mod crs;
pub mod index;
pub mod quantized_mesh;
pub mod source;
pub mod tiling;
