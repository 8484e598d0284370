//! Test harnesses shared by every test that needs them: the chi-square test of a sampler against
//! its pdf, and known-answer helpers. Public so that integration tests and examples reuse them.

pub mod chi2;
