"""Camera models behind one interface (`calibration.models.base.CameraModel`)."""
