"""From posed frames to ground truth: carving, meshing, smoothing, tight box, masks, REDWOOD75 export."""
