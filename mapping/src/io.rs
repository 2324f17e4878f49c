//! Parsers and writers for external file formats. Everything here reads `impl BufRead` / writes `impl Write`;
//! opening files is the caller's business.

pub mod g2o;
