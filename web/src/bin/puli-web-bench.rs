//! `puli-web-bench` (`puli bench web` runs it): what serving a fleet to
//! browsers and to Foxglove costs. See docs/web.md.

use clap::Parser;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    puli_web::bench::run(puli_web::bench::Args::parse()).await
}
