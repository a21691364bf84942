//! `sqlx::migrate!` embeds `../migrations/{sqlite,postgres}` at compile time; rebuild when it changes.
fn main() {
    println!("cargo:rerun-if-changed=../migrations/sqlite");
    println!("cargo:rerun-if-changed=../migrations/postgres");
}
