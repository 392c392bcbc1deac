//! Fixtures written at test time by `tests/fixtures/make_fixtures.py` with real numpy and
//! pickle (`$PYTHON`, else `python3`), once per test binary.

// Each test binary uses its own part of these helpers.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use glam::{Mat3, Vec3};

/// The fixture directory (generated on first use).
pub fn fixtures() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir =
            std::env::temp_dir().join(format!("dex2hoi-import-fixtures-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/make_fixtures.py");
        let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
        let output = std::process::Command::new(&python)
            .arg(&script)
            .arg(&dir)
            .output()
            .unwrap_or_else(|e| panic!("running {python} {}: {e}", script.display()));
        assert!(
            output.status.success(),
            "the fixture generator failed (it needs numpy and PyYAML; scripts/setup.sh installs \
             them):\n{}",
            String::from_utf8_lossy(&output.stderr)
        );
        dir
    })
}

/// A temporary output directory.
pub fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("dex2hoi-import-{name}-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    dir
}

/// The canonical frame of `features::canonicalise` applied to world points, from the root's
/// rotation and position at the first frame: a turn about +Y so that the root faces +Z, and
/// a horizontal shift that puts the first pelvis above the origin.
pub fn canonical(points: &[Vec3], root_rotation: Mat3, root_position: Vec3) -> Vec<Vec3> {
    let forward = root_rotation * Vec3::Z;
    let yaw = forward.x.atan2(forward.z);
    let turn = Mat3::from_axis_angle(Vec3::Y, -yaw);
    let shift = Vec3::new(root_position.x, 0.0, root_position.z);
    points.iter().map(|p| turn * (*p - shift)).collect()
}

/// A row-major 3x3 matrix from nine numbers.
pub fn mat3_rows(m: &[f64]) -> Mat3 {
    let row = |i: usize| Vec3::new(m[3 * i] as f32, m[3 * i + 1] as f32, m[3 * i + 2] as f32);
    dex2hoi_repr::rotation::mat3_from_rows(row(0), row(1), row(2))
}
