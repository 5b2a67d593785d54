//! Runs the Python client's unittest suite (clients/python/test_omnid_client.py) against
//! this build's `omnid serve`: every test class there starts its own simulated daemon.

use std::process::Command;

#[test]
#[ignore = "paced"]
fn python_client_suite_passes_against_a_real_daemon() {
    let root = env!("CARGO_MANIFEST_DIR");
    let output = match Command::new("python3")
        .args([
            "-m",
            "unittest",
            "-v",
            "clients/python/test_omnid_client.py",
        ])
        .current_dir(root)
        .env("OMNID_BIN", env!("CARGO_BIN_EXE_omnid"))
        // The suite chooses its own sockets and state directories.
        .env_remove("OMNID_SOCKET")
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .env("PYTHONUNBUFFERED", "1")
        .output()
    {
        Ok(o) => o,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => panic!(
            "python3 is not on PATH: the Python client's tests need Python ≥ 3.8 (standard \
             library only); install it or put it on PATH"
        ),
        Err(e) => panic!("cannot run python3: {e}"),
    };
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    // unittest reports on stderr; shown by `cargo test -- --nocapture` or on failure.
    println!("{stdout}{stderr}");
    assert!(
        output.status.success(),
        "python3 -m unittest clients/python/test_omnid_client.py failed ({}):\n{stdout}{stderr}",
        output.status
    );
    assert!(
        !stderr.contains("OMNID_BIN is not set"),
        "the Python suite skipped its daemon tests although OMNID_BIN was set:\n{stderr}"
    );
}
