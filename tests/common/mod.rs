//! Helpers shared by the integration tests: run the `omnid` binary, read its CSV logs.
#![allow(dead_code)]

use std::path::Path;
use std::process::{Command, Output};

pub fn omnid() -> Command {
    Command::new(env!("CARGO_BIN_EXE_omnid"))
}

pub fn run_ok(args: &[&str]) -> Output {
    let out = omnid().args(args).output().expect("omnid starts");
    assert!(
        out.status.success(),
        "omnid {args:?} failed: {}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// A parsed log: header and rows of fields.
pub struct Log {
    pub header: Vec<String>,
    pub rows: Vec<Vec<String>>,
}

impl Log {
    pub fn read(path: &Path) -> Log {
        let text = std::fs::read_to_string(path).expect("log readable");
        let mut lines = text.lines();
        let header: Vec<String> = lines
            .next()
            .expect("header")
            .split(',')
            .map(String::from)
            .collect();
        let rows: Vec<Vec<String>> = lines
            .map(|l| l.split(',').map(String::from).collect::<Vec<_>>())
            .collect();
        for (i, r) in rows.iter().enumerate() {
            assert_eq!(
                r.len(),
                header.len(),
                "row {} has {} fields",
                i + 2,
                r.len()
            );
        }
        Log { header, rows }
    }

    pub fn col(&self, name: &str) -> usize {
        self.header
            .iter()
            .position(|h| h == name)
            .unwrap_or_else(|| panic!("no column {name}"))
    }

    pub fn f64s(&self, name: &str) -> Vec<f64> {
        let c = self.col(name);
        self.rows
            .iter()
            .map(|r| r[c].parse::<f64>().expect("numeric"))
            .collect()
    }
}
