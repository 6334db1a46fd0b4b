document.getElementById('status').textContent = 'placeholder';
