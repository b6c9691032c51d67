"""File formats: the capture bundle (`bundle`, split into schema, write, read and summary) and
the calibration file (`calibration`). Both sit on the floor: acquire, sim and calibrate write
them, recon and the commands read them, and they import nothing above physics."""
