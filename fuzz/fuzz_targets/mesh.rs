//! OBJ and PLY meshes (through `tobj` and `ply-rs-bw`, guarded by our checks): the first byte
//! picks the format.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, bytes)) = data.split_first() else { return };
    let _ = if kind % 2 == 0 {
        dex2hoi_repr::Mesh::parse_obj(bytes, "fuzz.obj")
    } else {
        dex2hoi_repr::Mesh::parse_ply(bytes, "fuzz.ply")
    };
});
