//! `cargo xtask build-cuda`: the GPU build of dex2hoi, made on a machine without a GPU or a
//! CUDA installation, packed to be carried to one.
//!
//! candle's `cuda` feature needs, at build time, `nvcc` (its kernels are compiled to PTX and a
//! static library) and the CUDA libraries to link against (`cudarc` links the driver, NVRTC,
//! cuRAND and cuBLAS dynamically). Here:
//! 1. The CUDA 13.0 compiler, runtime and headers come from PyPI's `nvidia-*` wheels, installed
//!    with `pip --target` under `target/cuda-toolkit/` (once). nvcc stays at 13.0: the GPU
//!    machines' driver (580) supports CUDA 13.0 and cannot load PTX of a newer compiler.
//! 2. No wheel ships the driver's `libcuda.so`, and the other libraries are not needed to link:
//!    stand-ins are linked instead, shared libraries with the real sonames that define every
//!    function `cudarc` declares for them (read from its `sys` bindings; the bodies are empty
//!    and never run), so the binary records the right names and binds to the real libraries
//!    at run time. It therefore cannot start on a machine without the NVIDIA driver and the
//!    CUDA libraries: it is a separate binary, never the default. (`cudarc`'s
//!    `dynamic-loading` would avoid this, but candle asks for `dynamic-linking` and the two
//!    exclude each other.)
//! 3. `CUDA_COMPUTE_CAP=90` (H100 and H200; candle makes it sm_90a) since there is no GPU to
//!    ask.
//! 4. The `dex2hoi` binary and the `cuda` test executables are built into `target/cuda/`
//!    (release profile, one feature resolution for both), stripped and gzipped into
//!    `target/cuda-pack/` (`dex2hoi.gz`, `dex2hoi-train-cuda.gz`), with the CUPTI profiler
//!    `scripts/cuda-profile.c` compiled against CUPTI's wheel (`libdex2hoi-profile.so.gz`). That folder is what a GPU
//!    session carries; `scripts/gpu-check.sh` unpacks it there, finds the CUDA libraries of the
//!    machine's PyTorch, and runs the tests and the measurements.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

use crate::{cargo_program, run};

/// The pinned wheels of the CUDA 13.0 toolkit pieces the build needs.
const WHEELS: [&str; 5] = [
    "nvidia-cuda-nvcc==13.0.88",
    "nvidia-nvvm==13.0.88",
    "nvidia-cuda-runtime==13.0.96",
    "nvidia-cuda-crt==13.0.88",
    "nvidia-cuda-cccl==13.0.85",
];

/// The pinned wheel of CUPTI, whose headers and library the profiler (`scripts/cuda-profile.c`)
/// is compiled against; installed into a folder of its own.
const CUPTI_WHEEL: &str = "nvidia-cuda-cupti==13.0.85";

/// The libraries `cudarc` links, by soname, with the `cudarc` module whose `sys` bindings
/// declare their functions; stand-ins are linked here, the real ones load on the GPU machine.
const STAND_INS: [(&str, &str); 5] = [
    ("libcuda.so.1", "driver"),
    ("libnvrtc.so.13", "nvrtc"),
    ("libcurand.so.10", "curand"),
    ("libcublas.so.13", "cublas"),
    ("libcublasLt.so.13", "cublaslt"),
];

/// H100 and H200.
const COMPUTE_CAPABILITY: &str = "90";

/// The packages built, the binary's and the CUDA tests', always selected together so that one
/// feature resolution serves both builds (another selection changes some dependency's
/// features, and cargo then builds every dependency a second time).
const PACKAGES: [&str; 2] = ["dex2hoi-cli", "dex2hoi-train"];
const FEATURES: &str = "dex2hoi-cli/cuda,dex2hoi-train/cuda";

/// The CUDA test targets (in `dex2hoi-train`), packed as `dex2hoi-train-NAME`.
const CUDA_TESTS: [&str; 1] = ["cuda"];

/// Runs `cargo xtask build-cuda`.
pub fn build_cuda(root: &Path) -> Result<()> {
    let toolkit = toolkit(root)?;
    let target_dir = root.join("target/cuda");
    let path =
        format!("{}:{}", toolkit.join("bin").display(), std::env::var("PATH").unwrap_or_default());
    let cargo_command = |args: &[&str]| {
        let mut command = Command::new(cargo_program());
        command
            .args(args)
            .arg("--target-dir")
            .arg(&target_dir)
            .current_dir(root)
            .env("CUDA_HOME", &toolkit)
            .env("CUDA_PATH", &toolkit)
            .env("CUDA_COMPUTE_CAP", COMPUTE_CAPABILITY)
            .env("PATH", &path);
        command
    };
    let selection: Vec<&str> =
        PACKAGES.iter().flat_map(|p| ["-p", *p]).chain(["--features", FEATURES]).collect();
    let build: Vec<&str> =
        ["build", "--release", "--locked"].into_iter().chain(selection.clone()).collect();
    eprintln!("\n==> cargo {} (CUDA_HOME={})", build.join(" "), toolkit.display());
    run(&mut cargo_command(&build))?;
    let mut executables = vec![("dex2hoi".to_string(), target_dir.join("release/dex2hoi"))];
    for test in CUDA_TESTS {
        let args: Vec<&str> =
            ["test", "--release", "--locked", "--no-run", "--message-format=json"]
                .into_iter()
                .chain(selection.clone())
                .chain(["--test", test])
                .collect();
        eprintln!("\n==> cargo {}", args.join(" "));
        let output = cargo_command(&args)
            .stderr(std::process::Stdio::inherit())
            .output()
            .context("cannot run cargo test --no-run")?;
        if !output.status.success() {
            bail!("`cargo {}` failed ({})", args.join(" "), output.status);
        }
        let executable = test_executable(&output.stdout, test)
            .with_context(|| format!("cargo named no executable for the test `{test}`"))?;
        executables.push((format!("dex2hoi-train-{test}"), executable));
    }
    executables.push(("libdex2hoi-profile.so".to_string(), profiler(root, &toolkit)?));
    pack(root, &executables)
}

/// Compiles `scripts/cuda-profile.c`, the CUPTI injection library `scripts/gpu-check.sh`
/// profiles with, into `target/cuda/`.
fn profiler(root: &Path, toolkit: &Path) -> Result<PathBuf> {
    let cupti = root.join("target/cuda-toolkit/cupti");
    let cu13 = cupti.join("nvidia/cu13");
    if !cu13.join("include/cupti.h").exists() {
        eprintln!("\n==> pip install --no-deps --target {} {CUPTI_WHEEL}", cupti.display());
        run(Command::new("python3")
            .args(["-m", "pip", "install", "--quiet", "--no-deps", "--target"])
            .arg(&cupti)
            .arg(CUPTI_WHEEL))?;
    }
    let library = root.join("target/cuda/libdex2hoi-profile.so");
    eprintln!("\n==> cc scripts/cuda-profile.c -o {}", library.display());
    run(Command::new("cc")
        .args(["-std=c11", "-D_GNU_SOURCE", "-O2", "-Wall", "-Wextra", "-Werror"])
        .args(["-shared", "-fPIC", "-o"])
        .arg(&library)
        .arg(root.join("scripts/cuda-profile.c"))
        .arg(format!("-I{}", cu13.join("include").display()))
        .arg(format!("-I{}", toolkit.join("include").display()))
        .arg(format!("-L{}", cu13.join("lib").display()))
        .arg("-l:libcupti.so.13"))?;
    Ok(library)
}

/// The toolkit folder (`CUDA_HOME`): made once from the wheels, with the stand-in libraries.
fn toolkit(root: &Path) -> Result<PathBuf> {
    let base = root.join("target/cuda-toolkit");
    let home = base.join("home");
    let wheels = base.join("pkgs");
    let cuda = wheels.join("nvidia/cu13");
    if !cuda.join("bin/nvcc").exists() {
        eprintln!("\n==> pip install --no-deps --target {} {}", wheels.display(), WHEELS.join(" "));
        run(Command::new("python3")
            .args(["-m", "pip", "install", "--quiet", "--no-deps", "--target"])
            .arg(&wheels)
            .args(WHEELS))?;
    }
    let lib = home.join("lib64");
    std::fs::create_dir_all(&lib).with_context(|| format!("creating {}", lib.display()))?;
    for folder in ["bin", "include", "nvvm"] {
        link(&cuda.join(folder), &home.join(folder))?;
    }
    link(&cuda.join("lib/libcudart.so.13"), &lib.join("libcudart.so.13"))?;
    link(&lib.join("libcudart.so.13"), &lib.join("libcudart.so"))?;
    let bindings = cudarc_source(root)?.join("src");
    for (soname, module) in STAND_INS {
        let file = lib.join(soname);
        let declarations = bindings.join(module).join("sys/mod.rs");
        let text = std::fs::read_to_string(&declarations)
            .with_context(|| format!("reading {}", declarations.display()))?;
        let functions = linked_functions(&text);
        if functions.is_empty() {
            bail!("{} declares no linked function", declarations.display());
        }
        let source = base.join(format!("{soname}.c"));
        let mut c = String::from("/* A stand-in to link against: see xtask/src/cuda.rs. */\n");
        for function in &functions {
            c.push_str(&format!("void {function}(void) {{}}\n"));
        }
        std::fs::write(&source, c).with_context(|| format!("writing {}", source.display()))?;
        run(Command::new("cc")
            .args(["-shared", "-fPIC", "-o"])
            .arg(&file)
            .arg(format!("-Wl,-soname,{soname}"))
            .arg(&source))?;
        let unversioned = soname.split(".so").next().expect("a soname has a stem").to_string();
        link(&file, &lib.join(format!("{unversioned}.so")))?;
    }
    Ok(home)
}

/// The source folder of the `cudarc` the lock file names (from `cargo metadata`).
fn cudarc_source(root: &Path) -> Result<PathBuf> {
    let output = Command::new(cargo_program())
        .args(["metadata", "--format-version", "1", "--locked", "--all-features"])
        .current_dir(root)
        .output()
        .context("cannot run cargo metadata")?;
    if !output.status.success() {
        bail!("cargo metadata failed: {}", String::from_utf8_lossy(&output.stderr));
    }
    let metadata: serde_json::Value =
        serde_json::from_slice(&output.stdout).context("cargo metadata's output")?;
    let manifest = metadata["packages"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|p| p["name"] == "cudarc")
        .and_then(|p| p["manifest_path"].as_str())
        .context("Cargo.lock has no cudarc (the `cuda` features pull it in)")?;
    Ok(Path::new(manifest).parent().context("a manifest has a folder")?.to_path_buf())
}

/// The functions a `cudarc` binding module links (`extern "C" { fn name(`), in order, once each.
fn linked_functions(bindings: &str) -> Vec<String> {
    const OPENING: &str = "extern \"C\" {";
    let mut functions: Vec<String> = Vec::new();
    let mut rest = bindings;
    while let Some(at) = rest.find(OPENING) {
        rest = &rest[at + OPENING.len()..];
        let Some(declaration) = rest.trim_start().strip_prefix("fn ") else { continue };
        let name: String =
            declaration.chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
        if !name.is_empty() && !functions.contains(&name) {
            functions.push(name);
        }
    }
    functions
}

/// A symbolic link `to -> from` (replacing an old one).
fn link(from: &Path, to: &Path) -> Result<()> {
    if !from.exists() {
        bail!("{} is missing from the CUDA wheels", from.display());
    }
    let _ = std::fs::remove_file(to);
    std::os::unix::fs::symlink(from, to)
        .with_context(|| format!("linking {} to {}", to.display(), from.display()))
}

/// The executable of a test target in cargo's JSON messages.
fn test_executable(messages: &[u8], test: &str) -> Option<PathBuf> {
    String::from_utf8_lossy(messages).lines().find_map(|line| {
        let message: serde_json::Value = serde_json::from_str(line).ok()?;
        let target = message.get("target")?;
        let is_test = target.get("kind")?.as_array()?.iter().any(|k| k == "test");
        (is_test && target.get("name")? == test)
            .then(|| message.get("executable")?.as_str().map(PathBuf::from))
            .flatten()
    })
}

/// Strips and gzips the executables into `target/cuda-pack/`.
fn pack(root: &Path, executables: &[(String, PathBuf)]) -> Result<()> {
    let pack = root.join("target/cuda-pack");
    let _ = std::fs::remove_dir_all(&pack);
    std::fs::create_dir_all(&pack).with_context(|| format!("creating {}", pack.display()))?;
    let mut total = 0;
    for (name, executable) in executables {
        let stripped = pack.join(name);
        run(Command::new("strip").arg("-o").arg(&stripped).arg(executable))?;
        run(Command::new("gzip").arg("-9").arg(&stripped))?;
        let size = std::fs::metadata(pack.join(format!("{name}.gz")))?.len();
        total += size;
        eprintln!("packed {name}: {:.1} MiB", size as f64 / (1 << 20) as f64);
    }
    eprintln!(
        "\n{} ({:.1} MiB): carry it to a GPU machine and run `bash scripts/gpu-check.sh`",
        pack.display(),
        total as f64 / (1 << 20) as f64
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::linked_functions;

    #[test]
    fn linked_functions_are_read_from_the_bindings() {
        let bindings = r#"pub unsafe fn cuInit(flags: u32) -> CUresult {
            #[cfg(not(feature = "dynamic-loading"))]
            {
                extern "C" {
                    fn cuInit(flags: u32) -> CUresult;
                }
            }
        }
        type F = unsafe extern "C" fn(u32);
        extern "C" { fn cuDriverGetVersion(v: *mut i32); }
        extern "C" { fn cuInit(flags: u32); }"#;
        assert_eq!(linked_functions(bindings), ["cuInit", "cuDriverGetVersion"]);
    }
}
