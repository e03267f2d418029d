use volgrad::bridge::ffi;

fn asset(name: &str) -> String {
    format!("{}/scenes/assets/{}", env!("CARGO_MANIFEST_DIR"), name)
}

#[test]
fn explore() {
    for f in ["wdas_cloud_sixteenth.vdb", "smoke.vdb", "torus01.vdb", "tiny_sphere.vdb", "dragon_with_xform.vdb", "grids.vdb", "points.vdb"] {
        match ffi::list_grids(&asset(f)) {
            Ok(v) => for g in v { println!("{f}: {:#?}", g); },
            Err(e) => println!("{f}: ERR {e}"),
        }
    }
    let g = ffi::read_float_grid(&asset("wdas_cloud_sixteenth.vdb"), "density", -1).unwrap();
    let mut sizes = std::collections::BTreeMap::new();
    for (i, s) in g.tile_sizes.iter().enumerate() { *sizes.entry((*s, g.tile_values[i].to_bits())).or_insert(0) += 1; }
    println!("tiles {:?} leaves {}", sizes, g.leaf_origins.len() / 3);
    println!("{:?}", ffi::read_float_grid(&asset("points.vdb"), "", 0).err());
    println!("{:?}", ffi::read_float_grid(&asset("grids.vdb"), "x", -1).err());
    println!("{:?}", ffi::read_float_grid(&asset("grids.vdb"), "x", 7).err());
    println!("{:?}", ffi::read_float_grid(&asset("nope.vdb"), "x", 7).err());
}
