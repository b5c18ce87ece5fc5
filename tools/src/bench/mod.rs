//! Benchmarks: separate processes on loopback, measured, never timed tests.

pub mod call;
pub mod discovery;
pub mod fastpath;
