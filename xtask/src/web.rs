//! `cargo xtask web [--serve [PORT]]`: the static site of `crates/dex2hoi-web` in `target/web/`.
//!
//! The steps, each reused when already done:
//! 1. `dex2hoi-web` built for `wasm32-unknown-unknown` with SIMD128. rustup cannot fetch that
//!    target's standard library on machines that reach only the package registries, so the
//!    build takes Debian's `rustc-web` (`/usr/bin/rustc`, Rust 1.96) and rebuilds `std` from
//!    `rust-web-src` (`-Z build-std`, allowed by `RUSTC_BOOTSTRAP`), linked by the `rust-lld`
//!    of the rustup toolchain that runs xtask. `scripts/setup.sh` installs both packages.
//! 2. `wasm-bindgen` of the version `Cargo.lock` pins for the `wasm-bindgen` crate (they must
//!    be equal), installed from crates.io into `target/web-tools/`, writes the JavaScript glue.
//! 3. The page (`crates/dex2hoi-web/page/`), three.js from its pinned npm package (`npm ci`),
//!    and the shipped model (`crates/dex2hoi-cli/model/`) are copied beside it.
//!
//! `--serve` then serves the folder on `http://127.0.0.1:PORT/` (8000 by default) with the
//! content types a browser needs for modules and WebAssembly.

use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

use crate::{cargo_program, run};

/// Debian's `rustc-web` compiler and the standard library sources of `rust-web-src`.
const WEB_RUSTC: &str = "/usr/bin/rustc";
const WEB_CARGO: &str = "/usr/bin/cargo";
const WEB_RUST_SRC: &str = "/usr/lib/rustlib/src/rust/library";
const TARGET: &str = "wasm32-unknown-unknown";
/// getrandom's browser backend (`crypto.getRandomValues`) needs this `cfg` beside its feature.
const RUSTFLAGS: &str = "-C target-feature=+simd128 --cfg getrandom_backend=\"wasm_js\"";
/// The files of three.js the page imports, under `node_modules/three/`.
const THREE_FILES: [&str; 7] = [
    "LICENSE",
    "build/three.module.js",
    "build/three.core.js",
    "examples/jsm/loaders/GLTFLoader.js",
    "examples/jsm/controls/OrbitControls.js",
    "examples/jsm/utils/BufferGeometryUtils.js",
    "examples/jsm/utils/SkeletonUtils.js",
];
/// The page's own files.
const PAGE_FILES: [&str; 4] = ["index.html", "style.css", "main.js", "worker.js"];
/// Where the page finds the model.
const MODEL_FILE: &str = "model.safetensors";
/// The port `--serve` takes unless told.
const DEFAULT_PORT: u16 = 8000;

/// `cargo xtask web [--serve [PORT]]`.
pub fn web(root: &Path, args: &[String]) -> Result<()> {
    let serve_port = match args {
        [] => None,
        [flag] if flag == "--serve" => Some(DEFAULT_PORT),
        [flag, port] if flag == "--serve" => {
            Some(port.parse().with_context(|| format!("--serve PORT: not a port: {port}"))?)
        }
        _ => bail!("usage: cargo xtask web [--serve [PORT]]"),
    };
    let site = build_site(root)?;
    match serve_port {
        Some(port) => serve(&site, port),
        None => Ok(()),
    }
}

/// Builds the site into `target/web/` and returns its path.
pub fn build_site(root: &Path) -> Result<PathBuf> {
    for (path, what) in [
        (WEB_RUSTC, "Debian's rustc-web"),
        (WEB_CARGO, "Debian's cargo (with rustc-web)"),
        (WEB_RUST_SRC, "Debian's rust-web-src"),
    ] {
        if !Path::new(path).exists() {
            bail!("{path} is missing: the web build needs {what} (run scripts/setup.sh)");
        }
    }
    let site = root.join("target/web");
    let wasm = build_wasm(root)?;
    let bindgen = wasm_bindgen(root)?;
    std::fs::create_dir_all(&site).with_context(|| format!("creating {}", site.display()))?;
    eprintln!("\n==> wasm-bindgen --target web");
    run(Command::new(&bindgen)
        .args(["--target", "web", "--no-typescript", "--out-dir"])
        .arg(site.join("pkg"))
        .arg(&wasm))?;
    let page = root.join("crates/dex2hoi-web/page");
    if !page.join("node_modules/three/package.json").is_file() {
        eprintln!("\n==> npm ci (three.js, playwright-core)");
        run(Command::new("npm")
            .args(["ci", "--no-audit", "--no-fund", "--silent"])
            .current_dir(&page))?;
    }
    for file in PAGE_FILES {
        copy(&page.join(file), &site.join(file))?;
    }
    for file in THREE_FILES {
        copy(&page.join("node_modules/three").join(file), &site.join("vendor/three").join(file))?;
    }
    copy(&root.join("crates/dex2hoi-cli/model/dex2hoi-demo.safetensors"), &site.join(MODEL_FILE))?;
    report_sizes(&site)?;
    Ok(site)
}

/// `dex2hoi-web` for wasm32 with rustc-web and `-Z build-std`; returns the module's path.
fn build_wasm(root: &Path) -> Result<PathBuf> {
    let target_dir = root.join("target/wasm");
    let linker = rustup_lld()?;
    eprintln!(
        "\n==> cargo build --release --target {TARGET} -p dex2hoi-web (rustc-web, build-std)"
    );
    run(Command::new(WEB_CARGO)
        .args(["build", "--release", "--locked", "--target", TARGET])
        .args(["-Z", "build-std=std,panic_abort", "-p", "dex2hoi-web", "--target-dir"])
        .arg(&target_dir)
        .current_dir(root)
        .env("RUSTC", WEB_RUSTC)
        .env("RUSTC_BOOTSTRAP", "1")
        .env("CARGO_TARGET_WASM32_UNKNOWN_UNKNOWN_LINKER", linker)
        .env("CARGO_TARGET_WASM32_UNKNOWN_UNKNOWN_RUSTFLAGS", RUSTFLAGS)
        // The rustup toolchain's settings would otherwise reach Debian's cargo.
        .env_remove("RUSTUP_TOOLCHAIN")
        .env_remove("RUSTFLAGS")
        .env_remove("CARGO_ENCODED_RUSTFLAGS"))?;
    Ok(target_dir.join(TARGET).join("release/dex2hoi_web.wasm"))
}

/// The `rust-lld` of the rustup toolchain that runs xtask (the `rustc` beside its `cargo`: with
/// rustc-web installed, the `rustc` on the `PATH` may be Debian's).
fn rustup_lld() -> Result<PathBuf> {
    let cargo = PathBuf::from(cargo_program());
    let rustc = match cargo.parent() {
        Some(dir) if dir.join("rustc").is_file() => dir.join("rustc"),
        _ => PathBuf::from("rustc"),
    };
    let output = Command::new(&rustc)
        .args(["--print", "sysroot"])
        .output()
        .with_context(|| format!("cannot run {} --print sysroot", rustc.display()))?;
    let sysroot = String::from_utf8(output.stdout).context("rustc --print sysroot")?;
    let host = Command::new(&rustc).arg("-vV").output().context("cannot run rustc -vV")?;
    let host = String::from_utf8_lossy(&host.stdout)
        .lines()
        .find_map(|l| l.strip_prefix("host: ").map(str::to_string))
        .context("rustc -vV names no host")?;
    let lld = Path::new(sysroot.trim()).join("lib/rustlib").join(host).join("bin/rust-lld");
    if !lld.is_file() {
        bail!(
            "{} is missing: the web build links with the rustup toolchain's rust-lld",
            lld.display()
        );
    }
    Ok(lld)
}

/// The `wasm-bindgen` of the version Cargo.lock pins, installed into `target/web-tools/`.
fn wasm_bindgen(root: &Path) -> Result<PathBuf> {
    let version = locked_version(root, "wasm-bindgen")?;
    let tools = root.join("target/web-tools");
    let binary = tools.join("bin/wasm-bindgen");
    let installed = Command::new(&binary)
        .arg("--version")
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string());
    if installed.as_deref() != Some(&format!("wasm-bindgen {version}")) {
        eprintln!("\n==> cargo install wasm-bindgen-cli {version}");
        // Not `--locked`: its lock file names versions that crates.io mirrors may lack.
        run(Command::new(cargo_program())
            .args(["install", "--quiet", "wasm-bindgen-cli", "--version", &version, "--root"])
            .arg(&tools))?;
    }
    Ok(binary)
}

/// The version of a package in Cargo.lock.
fn locked_version(root: &Path, package: &str) -> Result<String> {
    let path = root.join("Cargo.lock");
    let lock: toml::Value = toml::from_str(
        &std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?,
    )
    .with_context(|| format!("parsing {}", path.display()))?;
    lock.get("package")
        .and_then(toml::Value::as_array)
        .into_iter()
        .flatten()
        .find(|p| p.get("name").and_then(toml::Value::as_str) == Some(package))
        .and_then(|p| p.get("version")?.as_str().map(str::to_string))
        .with_context(|| format!("{} has no package {package}", path.display()))
}

fn copy(from: &Path, to: &Path) -> Result<()> {
    if let Some(parent) = to.parent() {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating {}", parent.display()))?;
    }
    std::fs::copy(from, to)
        .with_context(|| format!("copying {} to {}", from.display(), to.display()))?;
    Ok(())
}

/// Prints the site's files with their sizes, raw and gzipped (`gzip -9`, as a static host
/// serves them).
fn report_sizes(site: &Path) -> Result<()> {
    let mut files = Vec::new();
    collect_files(site, &mut files)?;
    files.sort();
    let (mut raw, mut gzipped) = (0u64, 0u64);
    eprintln!("\n{:>10} {:>10}  file", "bytes", "gzip -9");
    for file in &files {
        let size = std::fs::metadata(file)?.len();
        let output = Command::new("gzip")
            .args(["-9", "-c"])
            .arg(file)
            .output()
            .context("cannot run gzip")?;
        let packed = output.stdout.len() as u64;
        raw += size;
        gzipped += packed;
        eprintln!("{size:>10} {packed:>10}  {}", file.strip_prefix(site).unwrap_or(file).display());
    }
    eprintln!("{raw:>10} {gzipped:>10}  in all: {}", site.display());
    Ok(())
}

fn collect_files(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    for entry in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let path = entry?.path();
        if path.is_dir() {
            collect_files(&path, out)?;
        } else {
            out.push(path);
        }
    }
    Ok(())
}

/// Serves `site` on `127.0.0.1:port` until interrupted, one thread per connection.
fn serve(site: &Path, port: u16) -> Result<()> {
    let listener = TcpListener::bind(("127.0.0.1", port))
        .with_context(|| format!("cannot listen on 127.0.0.1:{port}"))?;
    eprintln!("\nserving {} on http://127.0.0.1:{port}/ (Ctrl-C stops)", site.display());
    for stream in listener.incoming() {
        let Ok(stream) = stream else { continue };
        let site = site.to_path_buf();
        std::thread::spawn(move || {
            if let Err(error) = answer(&site, stream) {
                eprintln!("serve: {error:#}");
            }
        });
    }
    Ok(())
}

/// Answers one GET request with the file it names under `site` (`index.html` for a folder).
fn answer(site: &Path, mut stream: TcpStream) -> Result<()> {
    let mut request_line = String::new();
    BufReader::new(&stream).read_line(&mut request_line)?;
    let path = request_line.split_whitespace().nth(1).unwrap_or("/");
    let path = path.split(['?', '#']).next().unwrap_or("/");
    let relative = path.trim_start_matches('/');
    // No way out of the site: only plain names between slashes.
    let safe = relative.split('/').all(|part| part != ".." && !part.contains('\\'));
    let mut file = site.join(relative);
    if file.is_dir() {
        file = file.join("index.html");
    }
    match (safe, std::fs::read(&file)) {
        (true, Ok(body)) => {
            let header = format!(
                "HTTP/1.1 200 OK\r\nContent-Type: {}\r\nContent-Length: {}\r\nCache-Control: no-cache\r\nConnection: close\r\n\r\n",
                content_type(&file),
                body.len()
            );
            stream.write_all(header.as_bytes())?;
            stream.write_all(&body)?;
        }
        _ => {
            let body = format!("not found: {path}\n");
            let header = format!(
                "HTTP/1.1 404 Not Found\r\nContent-Type: text/plain\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                body.len()
            );
            stream.write_all(header.as_bytes())?;
            stream.write_all(body.as_bytes())?;
        }
    }
    Ok(())
}

/// The content type of a site file by its extension.
fn content_type(path: &Path) -> &'static str {
    match path.extension().and_then(|e| e.to_str()) {
        Some("html") => "text/html; charset=utf-8",
        Some("js") => "text/javascript; charset=utf-8",
        Some("css") => "text/css; charset=utf-8",
        Some("wasm") => "application/wasm",
        Some("json") => "application/json",
        Some("png") => "image/png",
        _ => "application/octet-stream",
    }
}
