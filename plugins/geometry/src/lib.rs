use grainpipe_core::Registry;
pub fn register(_r: &mut Registry) {}
