//! `aggtool convert` interrupted (issue 40's defect: SIGTERM during a convert left
//! `.NAME.agg.PID.tmp` beside the asset). The write's temporary file is registered
//! (`util::LiveTemp`) and the command line's handler removes it and exits with 130.
//! The test runs the built binary, as a user's shell or a farm's scheduler would signal it.

#![cfg(unix)]

mod common;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::{aggtool, ok};

/// Exit status of an interrupted command (`util::INTERRUPTED_EXIT_CODE`).
const INTERRUPTED: i32 = 130;

/// Margins: the temporary file appears once the asset is imported (well under a second for
/// 20,000 triangles; 120 s allows for a loaded 2-core machine), and the bake it is left in
/// (512³ under the `high` preset) runs for minutes on such a machine, so it is still running
/// when the signal is sent milliseconds later. After the signal the process exits as soon as
/// the handler thread runs (milliseconds; 60 s allowed). Polling every 20 ms, the test takes
/// about as long as `gen` and two imports.
const APPEAR: Duration = Duration::from_secs(120);
const EXIT: Duration = Duration::from_secs(60);

/// Waits up to `limit` for `done`, polling; whether it became true.
fn wait_for(limit: Duration, mut done: impl FnMut() -> bool) -> bool {
    let t = Instant::now();
    while t.elapsed() < limit {
        if done() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    done()
}

fn names_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// SIGTERM and SIGINT during `convert`'s bake: the temporary file beside the output is
/// removed, no output is written, the status is 130 and stderr says why.
#[test]
fn interrupted_convert_removes_its_temporary_file() {
    let d = tempfile::tempdir().unwrap();
    let logs = tempfile::tempdir().unwrap();
    ok(&aggtool(
        &["gen", "foliage", "-o", ".", "--triangles", "20000"],
        d.path(),
    ));
    for signal in ["TERM", "INT"] {
        let log = logs.path().join(format!("{signal}.log"));
        let mut child = Command::new(env!("CARGO_BIN_EXE_aggtool"))
            .args([
                "convert",
                "foliage.glb",
                "-o",
                "out.agg",
                "--preset",
                "high",
                "--max-res",
                "512",
            ])
            .current_dir(d.path())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("run aggtool");
        let pid = child.id();
        let tmp = d.path().join(format!(".out.agg.{pid}.tmp"));
        let mut exited_early = None;
        let appeared = wait_for(APPEAR, || {
            exited_early = child.try_wait().unwrap();
            exited_early.is_some() || tmp.exists()
        });
        if !appeared || exited_early.is_some() {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "SIG{signal}: no {} within {APPEAR:?} of the start (exited: {exited_early:?}); stderr: {}",
                tmp.display(),
                std::fs::read_to_string(&log).unwrap_or_default()
            );
        }
        let sent = Command::new("kill")
            .args([format!("-{signal}"), pid.to_string()])
            .status()
            .expect("run kill");
        assert!(sent.success(), "kill -{signal} {pid}");
        let mut status = None;
        let exited = wait_for(EXIT, || {
            status = child.try_wait().unwrap();
            status.is_some()
        });
        if !exited {
            let _ = child.kill();
            let _ = child.wait();
            panic!("SIG{signal}: still running {EXIT:?} after the signal");
        }
        let err = std::fs::read_to_string(&log).unwrap();
        assert_eq!(
            status.unwrap().code(),
            Some(INTERRUPTED),
            "SIG{signal}: {err}"
        );
        assert!(
            err.contains(&format!("interrupted (SIG{signal})")),
            "SIG{signal}: {err}"
        );
        assert!(!err.contains("panicked"), "{err}");
        assert!(!tmp.exists(), "SIG{signal}: {} left behind", tmp.display());
        assert_eq!(names_in(d.path()), ["foliage.glb"], "SIG{signal}");
    }
}
