//! Benchmarks: separate processes on loopback, measured, never timed tests.

pub mod discovery;
pub mod fastpath;
