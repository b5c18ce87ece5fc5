// Cargo unifies a package's build dependencies only when it has a build
// script: this one makes the [build-dependencies] above count.
fn main() {}
