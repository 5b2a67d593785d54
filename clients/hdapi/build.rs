//! The library's SONAME: programs linked against the vendor's 3.4 library look for it by
//! this name (docs/HDAPI.md, Library names).
fn main() {
    println!("cargo:rustc-cdylib-link-arg=-Wl,-soname,libHD.so.3.4");
}
