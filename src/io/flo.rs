//! Middlebury `.flo` flow files and the flow colour wheel (placeholder, being written).
