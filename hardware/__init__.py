"""glossrig.hardware: device protocols (lights, camera, engraver), their real and
virtual implementations, and the capture orchestrator.

Modules (each names the thesis section it implements):

* :mod:`.lights` - ``Lights`` protocol; ``GpioRelayLights`` (active-low relay module on
  Raspberry Pi GPIO, thesis 4.1.1), ``NumatoRelayLights`` (USB/serial relay board).
* :mod:`.camera` - ``Camera`` protocol; ``Gphoto2Camera`` (python-gphoto2, thesis 4.1.2);
  ``confirm_shot`` checks every raw file's own exposure metadata.
* :mod:`.engraver` - ``Engraver`` protocol; ``GrblEngraver`` (G-code), ``RolandEngraver``
  (RML-1, thesis 5.1.1), ``SimulatedEngraver``; :mod:`.toolpath_check` refuses a toolpath
  outside the bed or below the safe depth before anything is sent.
* :mod:`.plan` - capture plans (thesis 4.2.3) and their time estimate;
  :mod:`.orchestrator` - ``run_capture``: the resumable capture into a capture folder;
  :mod:`.operator` / :mod:`.progress` - the person at the rig and the progress bar.
* :mod:`.backends` / :mod:`.backends_twin` - ``--lights`` / ``--camera`` choices, the twin
  (one :class:`glossrig.twin.virtual_rig.VirtualRig` behind lights, camera and operator).
* :mod:`.fakes`, :mod:`.serial_sims` - test doubles at the device boundary (a fake
  gphoto2 binding, pty-simulated relay board, GRBL and Roland machines).
"""
